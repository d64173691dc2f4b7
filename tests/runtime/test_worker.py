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
from tests.runtime.bridge_helpers import read_file_header, read_frame, start_bridge

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
