"""Every device option check names its key (issue: option errors other than paths and unknown
options pointed at the device's ``[[devices]]`` line): a bad value stops the bridge with
``scenario.toml:<line of the key>: [devices.<name>.<option>]: ...``, before anything opens."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import pytest

from hilsim.config import ConfigError
from hilsim.resources import find_scenario
from hilsim.runtime.bridge import Bridge

DEFAULT = find_scenario("water_tank").read_text()


def with_option(device: str, key: str, value: str) -> tuple[str, int]:
    """The default scenario with ``key = value`` in device ``device``'s table (replacing the key if the
    table has it), and the line number of that key."""
    start = DEFAULT.index(f'name = "{device}"')
    end = DEFAULT.find("[[devices]]", start)
    end = len(DEFAULT) if end < 0 else end
    table = DEFAULT[start:end]
    line = f"{key} = {value}"
    m = re.search(rf"^{re.escape(key)} = .*$", table, flags=re.M)
    if m:
        table = table[:m.start()] + line + table[m.end():]
    else:
        first = table.index("\n") + 1
        table = table[:first] + line + "\n" + table[first:]
    text = DEFAULT[:start] + table + DEFAULT[end:]
    return text, text[:text.index(line, start)].count("\n") + 1


CASES = [
    ("sonar_ddf", "frame_rate_hz", "90", "outside"),
    ("sonar_ddf", "gain_db", "77", "outside"),
    ("sonar_ddf", "sensor", '"camera"', "not a sonar"),
    ("sonar_oculus", "max_rows", "4", "outside"),
    ("sonar_oculus", "profile_hf", '"no_such_sonar"', "no_such_sonar"),
    ("sonar_aris", "max_datagram", "70000", "outside"),
    ("sonar_aris", "system_type", '"big"', "integer"),
    ("depth", "device_id", "300", "outside"),
    ("depth", "parity", '"X"', "parity"),
    ("depth", "transport", '["serial"]', "transport"),
    ("imu", "rate", "-5", "outside"),
    ("vesc_can", "transport", '"carrier-pigeon"', "transport"),
    ("vesc_can", "channel", '""', "channel"),
    ("vesc_can", "status_rate_hz", "0", "outside"),
    ("vesc_can", "mapping", '{ 1 = "no_such_thruster" }', "no_such_thruster"),
    ("dronecan_esc", "node_id", "200", "outside"),
    ("dronecan_esc", "bitrate", "-1", "bitrate"),
    ("vesc_uart", "controller_id", "99", "not in the mapping"),
    ("vesc_uart", "baudrate", "12345", "serial rate"),
    ("vrcsr", "group_id", "999", "outside"),
    ("vrcsr", "node_ids", "5", "node_ids"),
]


@pytest.mark.parametrize("device, key, value, says", CASES, ids=[f"{d}.{k}" for d, k, _, _ in CASES])
def test_a_bad_option_names_its_line_and_key(tmp_path: Path, device, key, value, says):
    text, line = with_option(device, key, value)
    path = tmp_path / "scenario.toml"
    path.write_text(text)

    async def main() -> None:
        bridge = Bridge(path, fast=True, status_interval=0, run_dir=tmp_path / "run")
        try:
            with pytest.raises(ConfigError) as info:
                await bridge.start()
        finally:
            await bridge.close()
        msg = str(info.value)
        assert f"scenario.toml:{line}: [devices.{device}.{key}]" in msg, msg
        assert says in msg, msg
        assert bridge.worker.pid is None  # refused before anything started

    asyncio.run(main())
