"""The render worker: crashes and hangs are survived, the gap shows, the rest never stops."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import socket
import time

import numpy as np
import pytest

from hilsim.devices.base import RenderFailed
from hilsim.resources import find_profile, find_scenario
from hilsim.runtime.worker import RenderWorker
from hilsim.sim.geometry import Pose
from tests.runtime.bridge_helpers import read_file_header, read_frame, recv_exact, start_bridge

POSE = Pose.from_xyz_rpy((-1.35, 0.0, 1.8), (0.0, np.radians(-45), 0.0))


def test_worker_renders_survives_a_crash_and_a_hang():
    async def main():
        w = RenderWorker(find_scenario(None), seed=1, timeout=3.0)
        await w.start()
        prof = str(find_profile("sonars", "didson_hf"))
        frame, secs, alt = await w.render_sonar(prof, POSE, None, 0.0, 0, (-1.75, 0.0, 1.2))
        assert frame.image.shape == (512, 96) and secs > 0 and alt == pytest.approx(1.8)
        pid = w.pid
        with pytest.raises(RenderFailed):
            await w.call("crash")
        assert w.restarts == 1 and w.pid != pid
        frame2, _, _ = await w.render_sonar(prof, POSE, None, 0.0, 0, (0, 0, 0))
        assert np.array_equal(frame.image, frame2.image)  # same seed, same frame: same bytes after restart
        with pytest.raises(RenderFailed, match="did not answer"):
            await w.call("hang", 30.0, timeout=1.0)
        assert w.restarts == 2
        frame3, _, _ = await w.render_sonar(prof, POSE, None, 0.0, 0, (0, 0, 0))
        assert np.array_equal(frame.image, frame3.image)
        await w.close()
        assert w.pid is None

    asyncio.run(asyncio.wait_for(main(), 120))


def worker_pid(log: str) -> int:
    pids = re.findall(r"render worker started \(pid (\d+)\)", log)
    return int(pids[-1])


@pytest.mark.parametrize("fault", ["kill", "stop"])
def test_bridge_keeps_streaming_through_a_worker_crash_or_hang(tmp_path, fault):
    b = start_bridge(tmp_path, "--render-timeout", "1.5", "--status-interval", "1")
    try:
        s = socket.create_connection(b.tcp("ddf-stream"), timeout=30)
        read_file_header(s)
        before = [read_frame(s, 96, 512).number for _ in range(3)]
        pid = worker_pid(b.log())
        os.kill(pid, signal.SIGKILL if fault == "kill" else signal.SIGSTOP)
        t0 = time.monotonic()
        after = [read_frame(s, 96, 512).number for _ in range(8)]
        resumed_after = time.monotonic() - t0
        s.close()
        time.sleep(1.5)  # one more status line after the restart
        log = b.log()
        assert "restarting it" in log, log[-2000:]
        assert worker_pid(log) != pid
        # frames resume, and the lost ping shows as one gap in the frame numbers
        # (frames already queued before the fault may still arrive first)
        seq = before + after
        gaps = [(a, b) for a, b in zip(seq, seq[1:]) if b != a + 1]
        assert len(gaps) == 1 and gaps[0][1] > gaps[0][0] + 1, seq
        assert resumed_after < 30
        # the physics never stopped: the status lines kept coming while the worker was down
        times = [float(x) for x in re.findall(r"t=([0-9.]+)s depth", log)]
        assert len(times) >= 3 and times == sorted(times)
    finally:
        if fault == "stop":
            try:
                os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, UnboundLocalError):
                pass
        assert b.stop() == 0


# ------------------------------------------------------------ deadline-aware rendering (issue #15)

from hilsim.runtime.worker import (  # noqa: E402
    ADAPT_CALM, ADAPT_HIGH, ADAPT_LOW, ADAPT_STEP, ADAPT_TARGET, RayGovernor)


def test_ray_governor_lowers_on_a_missed_budget_never_below_the_floor_and_recovers_with_slack():
    g = RayGovernor(1000, 100)
    assert g.levels[0] == 1000 and g.levels[-1] == 100 and g.levels == sorted(g.levels, reverse=True)
    for a, b in zip(g.levels, g.levels[1:-1]):
        assert b == round(1000 * ADAPT_STEP ** g.levels.index(b)) and b < a
    for _ in range(50):  # fast frames: full quality stays
        g.update(0.1 * ADAPT_LOW, 0.1)
    assert g.rays == 1000
    g.update(0.1 * (ADAPT_HIGH + 0.01), 0.1)  # just over: one level down
    assert g.rays == g.levels[1]
    g.update(0.5, 0.1)  # 5x over its budget: enough levels for ~ADAPT_TARGET at cost ~ rays
    assert g.rays <= 1000 * ADAPT_TARGET / 5 * 1.5 or g.rays == 100
    assert ADAPT_LOW / ADAPT_STEP < ADAPT_HIGH  # a level up from the slack band does not overshoot at once
    for _ in range(20):  # a hopeless machine: the floor, never below
        g.update(10.0, 0.1)
    assert g.rays == 100
    g.update(0.1 * (ADAPT_LOW + ADAPT_HIGH) / 2, 0.1)  # in the band: stays
    assert g.rays == 100
    for k in range(ADAPT_CALM - 1):  # slack, but not yet for long enough
        g.update(0.01, 0.1)
    assert g.rays == 100
    g.update(0.01, 0.1)
    assert g.rays == g.levels[-2]
    for _ in range(ADAPT_CALM * len(g.levels)):
        g.update(0.01, 0.1)
    assert g.rays == 1000
    assert RayGovernor(64, 16).levels[-1] == 16 and RayGovernor(50, 100).levels == [50]


def test_worker_lowers_the_ray_count_for_a_tight_budget_and_raises_it_with_slack(tmp_path):
    """A budget no frame can meet takes the frames to the profile's floor (and their image
    keeps its echo: no empty bins where the floor is seen); a generous one brings the full
    count back; no budget, or a profile with adaptive_rays = false, always renders the full count."""
    prof = find_profile("sonars", "didson_hf")
    fixed = tmp_path / "didson_fixed.toml"
    fixed.write_text(prof.read_text().replace("adaptive_rays      = true", "adaptive_rays      = false"))
    assert "adaptive_rays      = false" in fixed.read_text()

    from hilsim.sim.sonar_profile import load_sonar_profile

    quiet = load_sonar_profile(prof).default_settings().realism_off()  # an empty bin stays empty

    async def main():
        w = RenderWorker(find_scenario(None), seed=1, timeout=20.0)
        await w.start()
        try:
            full, _, _ = await w.render_sonar(str(prof), POSE, quiet, 0.0, 0)
            assert full.settings.elevation_rays == 1000 and full.n_rays == 96 * 1000
            rays = []
            for i in range(6):
                f, _, _ = await w.render_sonar(str(prof), POSE, quiet, 0.0, i, budget_s=1e-4)
                rays.append(f.settings.elevation_rays)
                assert f.n_rays == 96 * f.settings.elevation_rays
            assert rays[0] == 1000 and rays[-1] == 100 and rays == sorted(rays, reverse=True), rays
            low = f
            # the floor's echo, per beam, over the same range rows as at full count: no empty bins
            rows = np.flatnonzero((full.intensity > 0).all(axis=1))
            assert rows.size > 20 and (low.intensity[rows] > 0).all()
            # the image level of the lit rows is the same (energy per ray is 1 / rays)
            assert np.median(low.intensity[rows] / full.intensity[rows]) == pytest.approx(1.0, rel=0.25)
            up = []
            for i in range(ADAPT_CALM * 8 + 2):
                f, _, _ = await w.render_sonar(str(prof), POSE, quiet, 0.0, i, budget_s=100.0)
                up.append(f.settings.elevation_rays)
            assert up == sorted(up) and up[-1] == 1000, up
            for i in range(3):  # fixed quality: the budget changes nothing
                f, _, _ = await w.render_sonar(str(fixed), POSE, None, 0.0, i, budget_s=1e-4)
                assert f.settings.elevation_rays == 1000
        finally:
            await w.close()

    asyncio.run(asyncio.wait_for(main(), 120))


def test_bridge_frames_and_status_line_state_the_ray_count(tmp_path):
    """Each DDF frame header states its elevation rays per beam at offset 732 (read here with
    struct, protocols/ddf-stream.md): within the profile's [min_elevation_rays, elevation_rays]
    = [100, 1000]; the status line shows the sonar's rays too."""
    from tests.runtime.abuse_clients import last_status

    b = start_bridge(tmp_path, "--status-interval", "0.5")
    try:
        s = socket.create_connection(b.tcp("ddf-stream"), timeout=30)
        read_file_header(s)
        frames = [read_frame(s, 96, 512) for _ in range(6)]
        rays = [int.from_bytes(f.raw[732:736], "little", signed=True) for f in frames]
        assert all(100 <= r <= 1000 for r in rays), rays
        deadline = time.monotonic() + 10
        st = None
        while time.monotonic() < deadline:
            read_frame(s, 96, 512)
            st = last_status(b.log())
            if st and st["devices"].get("sonar_ddf", {}).get("rays"):
                break
        s.close()
        assert st is not None and 100 <= st["devices"]["sonar_ddf"]["rays"] <= 1000, st
        # the Oculus: a v2 SimplePingResult carries them in its first spare u32 (@174,
        # protocols/oculus.md), within the M750d profile's [16, 64]
        from hilsim.protocols import oculus as oc

        with socket.create_connection(b.tcp("oculus"), timeout=30) as o:
            o.sendall(oc.encode_fire(oc.Fire(master_mode=oc.MODE_HF, ping_rate=3, flags=0x09, range=3.0,
                                             gain=100.0, version=2)))
            got = []
            while len(got) < 3:
                head = recv_exact(o, 16)
                assert head[:2] == b"SO"
                msg = head + recv_exact(o, int.from_bytes(head[10:14], "little"))
                if int.from_bytes(head[6:8], "little") == 0x23:
                    got.append(int.from_bytes(msg[174:178], "little"))
        assert all(16 <= r <= 64 for r in got), got
    finally:
        assert b.stop() == 0
