"""The soak (benchmarks/soak.py) for 30 s: the default scenario with every device, well-behaved
clients on each and abusive ones cycling through every kind (connect floods, idle, half-closed,
never-reading and stalled-huge-header clients, a byte blaster, a Modbus request flood, a CAN
flood). Zero lost replies to the well-behaved clients; file descriptors flat and memory
bounded after the warm-up (one full turn of the abuse kinds)."""

from __future__ import annotations

import importlib.util

import pytest

from tests.runtime.bridge_helpers import ROOT

pytestmark = [pytest.mark.alone, pytest.mark.timeout(180)]  # alone: both cores (make test)


def load_soak():
    spec = importlib.util.spec_from_file_location("hilsim_soak", ROOT / "benchmarks" / "soak.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_soak_30_seconds(tmp_path):
    lines: list[str] = []

    def out(line: str) -> None:
        print(line)
        lines.append(line)

    r = load_soak().main(minutes=0.5, out=out, workdir=tmp_path)
    assert lines[-1].startswith("VERDICT:")
    assert r["bridge_exit"] == 0, r["log"]
    assert r["errors"] == {}, r["errors"]  # no well-behaved client was ever disconnected
    assert r["lost_replies"] == 0 and r["ddf_gaps"] == 0
    assert all(n > 0 for n in r["served"].values()), r["served"]
    measured = [row for row in r["rows"] if not row["warmup"]]
    assert len(measured) >= 4
    # every client kept being served after the warm-up
    for name in r["served"]:
        assert sum(row["served"][name] for row in measured) > 0, name
    # descriptors flat (quiet points after each cycle), memory bounded
    assert r["fds_spread"] <= 3, r["fds_after_warmup"]
    assert max(r["fds_after_warmup"]) <= min(row["fds"] for row in r["rows"]) + 3
    assert max(r["rss_after_warmup"]) - min(r["rss_after_warmup"]) < 40, r["rss_after_warmup"]
    assert max(r["rss_after_warmup"]) < max(row["rss_mb"] for row in r["rows"] if row["warmup"]) + 30
