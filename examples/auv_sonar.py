"""The DIDSON-like DDF stream over TCP (protocols/ddf-stream.md), the simulation clock read from its
frame headers, and the target detector that reads the frames.
"""

from __future__ import annotations

import calendar
import math
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

FILE_HEADER = 1024
FRAME_HEADER = 1024
HF_START_M = 0.419          # extended windows, standard model: start code x this at HF (x 2 at LF)
LENGTHS_M = [1.25, 2.5, 5.0, 10.0, 20.0, 40.0]  # length code at HF, code + 2 at LF


def window_m(start_code: int, length_code: int, high_freq: bool) -> tuple[float, float]:
    """(start [m], length [m]) of the DIDSON extended window codes."""
    return start_code * HF_START_M * (1 if high_freq else 2), LENGTHS_M[length_code + (0 if high_freq else 2)]


def frame_time_s(header: bytes) -> float:
    """The frame time [s since the epoch]: the uint64 microseconds at offset 4 when they agree with the
    calendar fields (offsets 20..44) to 1/100 s, else the calendar fields."""
    micros = struct.unpack_from("<Q", header, 4)[0]
    y, mo, d, h, mi, s, hs = struct.unpack_from("<7i", header, 20)
    try:
        cal = calendar.timegm((y, mo, d, h, mi, s, 0, 0, 0)) + hs / 100.0
    except (ValueError, OverflowError):
        return micros / 1e6
    return micros / 1e6 if abs(micros / 1e6 - cal) < 0.011 else cal


@dataclass
class Detection:
    """What the detector says about one frame. Ranges [m] from the sonar; NaN when not measured."""
    found: bool
    shadow_edge: float       # far edge of the echo in the centre beams: the target's shadow starts here
    near_edge: float         # nearest strong return in the centre beams
    floor_far: float         # the floor's far edge expected in the centre beams (from the outer beams)
    floor_near: float
    contrast: float          # floor_far - shadow_edge [m]


def _band(profile: np.ndarray, ranges: np.ndarray, threshold: float, max_gap: int = 4) -> tuple[float, float]:
    """Near and far edge [m] of the first echo band: from the first sample at or above ``threshold`` to
    the last one before a gap of more than ``max_gap`` samples below it (speckle holes are shorter);
    crossings interpolated linearly between samples. NaN, NaN when nothing reaches the threshold."""
    above = np.nonzero(profile >= threshold)[0]
    if len(above) == 0:
        return math.nan, math.nan
    breaks = np.nonzero(np.diff(above) > max_gap + 1)[0]
    i, j = int(above[0]), int(above[breaks[0]] if len(breaks) else above[-1])

    def cross(a: int, b: int) -> float:  # between samples a and b, on either side of the threshold
        pa, pb = float(profile[a]), float(profile[b])
        f = 0.5 if pa == pb else (threshold - pa) / (pb - pa)
        return float(ranges[a] + f * (ranges[b] - ranges[a]))

    near = cross(i - 1, i) if i > 0 else float(ranges[i])
    far = cross(j, j + 1) if j + 1 < len(profile) else float(ranges[j])
    return near, far


class TargetDetector:
    """Finds an object standing on the floor ahead from the shadow it cuts into the floor echo.

    The sonar looks 45 deg down, so every beam sees a band of floor between the
    ranges where the lowest and highest rays of its +-7 deg elevation aperture
    reach it. The outer beams (|azimuth| >= 11 deg) see only floor and give that
    band; the centre beams (|azimuth| <= 2.4 deg) look at the target. An object
    standing on the floor hides the floor behind it, so the echo in the centre
    beams ends early: at the slant range of the object's foot (where its front
    face meets the floor), the start of its acoustic shadow.

    Per frame: mean intensity against range over each beam group, smoothed over
    3 samples. Threshold = the floor's peak level (outer beams) minus ``drop``
    levels (40 of 255, about 12 dB on an 80 dB display): well above the noise
    and the beam pattern's side lobes (about 35 dB down), and below the target's
    own echo (a plastic target returns a few dB less than concrete). Edges of the
    first echo band (``_band``), interpolated between samples. The outer groups'
    far edge times cos(azimuth) (a flat floor is nearer along the centre beams)
    predicts the floor's far edge in the centre; the farther of the two sides is
    taken (for the near edge too: an object seen by one side comes nearer than
    the floor), so an object seen by one side does not hide the floor. Detected when
    the centre echo ends ``min_contrast`` before that prediction. The target
    range is that shadow edge; the nearest strong return in the centre beams
    (near edge) is reported too: at close range the front face comes nearer
    than the floor.
    """

    def __init__(self, n_beams: int, fov_deg: float = 29.0, centre_half_deg: float = 2.4,
                 outer_from_deg: float = 11.0, drop: float = 40.0, min_contrast: float = 0.05) -> None:
        az = np.linspace(fov_deg / 2, -fov_deg / 2, n_beams)  # wire order: beam 0 is starboard
        self.centre = np.nonzero(np.abs(az) <= centre_half_deg)[0]
        self.sides = [np.nonzero(az >= outer_from_deg)[0], np.nonzero(az <= -outer_from_deg)[0]]
        self.side_cos = [float(np.mean(np.cos(np.radians(az[s])))) for s in self.sides]
        self.drop = drop
        self.min_contrast = min_contrast

    @staticmethod
    def _profile(img: np.ndarray, beams: np.ndarray) -> np.ndarray:
        p = img[:, beams].mean(axis=1)
        return np.convolve(p, np.ones(3) / 3.0, mode="same")

    def __call__(self, img: np.ndarray, ranges: np.ndarray) -> Detection:
        """img: (n_samples, n_beams) uint8, wire order; ranges: (n_samples,) [m] bin centres."""
        nothing = Detection(False, math.nan, math.nan, math.nan, math.nan, math.nan)
        sides = [self._profile(img, s) for s in self.sides]
        peak = max(float(p.max()) for p in sides)
        thr = peak - self.drop
        if thr < 0.25 * peak:  # no clear floor echo to compare against
            return nothing
        floor = [(_band(p, ranges, thr), c) for p, c in zip(sides, self.side_cos)]
        fars = [f[1] * c for f, c in floor if math.isfinite(f[1])]
        nears = [f[0] * c for f, c in floor if math.isfinite(f[0])]
        if not fars:
            return nothing
        near, far = _band(self._profile(img, self.centre), ranges, thr)
        contrast = max(fars) - far if math.isfinite(far) else math.nan
        found = bool(math.isfinite(contrast) and contrast >= self.min_contrast)
        return Detection(found, far, near, max(fars), max(nears), contrast)


@dataclass
class SonarFrame:
    number: int
    time: float              # [s since the epoch] frame time
    arrival: float           # [s] time.monotonic() at arrival
    detection: Detection
    depth: float             # header fields, for the log only
    heading: float


class DdfSonar:
    """Reads the DDF stream in a thread: frames -> SimClock samples and detections."""

    def __init__(self, host: str, port: int, rate_hz: float | None, clock: "SimClock",
                 detector_factory: Callable[[int], TargetDetector]) -> None:
        self.sock = socket.create_connection((host, port), timeout=10.0)
        self.clock = clock
        fh = self._read(FILE_HEADER)
        if fh[:4] != b"DDF\x04":
            raise ValueError(f"not a DDF version 4 stream: {fh[:4]!r}")
        self.high_freq = struct.unpack_from("<i", fh, 12)[0] == 1
        self.n_beams = struct.unpack_from("<i", fh, 16)[0]
        self.n_samples = struct.unpack_from("<i", fh, 24)[0]
        self.detector = detector_factory(self.n_beams)
        self.frames: deque[SonarFrame] = deque()   # new frames for the control loop
        self.lock = threading.Lock()
        self.received = 0
        self.lost = 0
        self.replies: list[str] = []
        self.error: str | None = None
        self._last_number: int | None = None
        self._stop = False
        if rate_hz is not None:
            self.sock.sendall(f"RATE {rate_hz:g}\n".encode("ascii"))
        self.thread = threading.Thread(target=self._run, name="ddf", daemon=True)
        self.thread.start()

    def _read(self, n: int) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            k = self.sock.recv_into(view[got:], n - got)
            if k == 0:
                raise EOFError("sonar stream closed")
            got += k
        return bytes(buf)

    def _run(self) -> None:
        self.sock.settimeout(None)
        size = self.n_beams * self.n_samples
        try:
            while not self._stop:
                hdr = self._read(FRAME_HEADER)
                data = self._read(size)
                arrival = time.monotonic()
                number = struct.unpack_from("<i", hdr, 0)[0]
                t = frame_time_s(hdr)
                start_code, length_code = struct.unpack_from("<ii", hdr, 52)
                depth, heading = struct.unpack_from("<f", hdr, 128)[0], struct.unpack_from("<f", hdr, 152)[0]
                reply = hdr[768:].split(b"\0", 1)[0].decode("ascii", "replace")
                start, length = window_m(start_code, length_code, self.high_freq)
                ranges = start + (np.arange(self.n_samples) + 0.5) * length / self.n_samples
                img = np.frombuffer(data, np.uint8).reshape(self.n_samples, self.n_beams)
                det = self.detector(img, ranges)
                self.clock.add(t, arrival)
                with self.lock:
                    if self._last_number is not None and number > self._last_number + 1:
                        self.lost += number - self._last_number - 1
                    self._last_number = number
                    self.received += 1
                    if reply:
                        self.replies.extend(reply.splitlines())
                    self.frames.append(SonarFrame(number, t, arrival, det, depth, heading))
        except (OSError, EOFError, ValueError) as e:
            if not self._stop:
                self.error = str(e)

    def take(self) -> list[SonarFrame]:
        with self.lock:
            out = list(self.frames)
            self.frames.clear()
            return out

    def close(self) -> None:
        self._stop = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self.thread.join(timeout=2.0)


class SimClock:
    """The simulation's clock, from (frame time, arrival) pairs. Thread-safe.

    A frame pinged at simulation time t_k arrives at monotonic time
    w_k = t_k / rate + c + latency_k, the latency (render, queues, a starved
    CPU) never negative and often large. So the clock is fitted to the lower
    envelope, the least-delayed frames: the rate (1 in real time, K under
    ``--time-scale K``) is the slope between the least-delayed frame of the
    oldest third of the history and that of the newest third (three passes,
    as "least delayed" depends on the rate), and now() extrapolates the
    least-delayed of the last 8 frames: max_k (t_k + rate (wall - w_k)).
    A long history makes the rate exact whatever the jitter."""

    def __init__(self, history: int = 600) -> None:
        self.samples: deque[tuple[float, float]] = deque(maxlen=history)
        self.lock = threading.Lock()
        self.rate = 1.0

    def add(self, t: float, wall: float) -> None:
        with self.lock:
            if self.samples and t <= self.samples[-1][0]:
                return
            self.samples.append((t, wall))
            if len(self.samples) < 3:
                return
            s = list(self.samples)
            third = max(1, len(s) // 3)
            rate = self.rate
            for _ in range(3):
                ta, wa = max(s[:third], key=lambda p: p[0] - rate * p[1])
                tb, wb = max(s[-third:], key=lambda p: p[0] - rate * p[1])
                if wb - wa < 0.05 or tb <= ta:
                    return
                rate = (tb - ta) / (wb - wa)
            self.rate = min(max(rate, 0.01), 1000.0)

    def ready(self) -> bool:
        with self.lock:
            return len(self.samples) >= 3

    def now(self, wall: float | None = None) -> float:
        wall = time.monotonic() if wall is None else wall
        with self.lock:
            return max(t + self.rate * (wall - w) for t, w in list(self.samples)[-8:])

    def wall_at(self, t_sim: float) -> float:
        with self.lock:
            return min(w + (t_sim - t) / self.rate for t, w in list(self.samples)[-8:])

    def last_frame_age(self) -> float:
        """[s] of simulation time since the newest frame's time."""
        with self.lock:
            t, w = self.samples[-1]
            return self.rate * (time.monotonic() - w)
