"""Pure conversions for the recorder: poses to quaternions, sonar frames to fan images,
readings to JSON. No I/O, no foxglove imports (the tests check them on their own)."""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
from scipy.spatial.transform import Rotation


def quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a (3, 3) rotation matrix."""
    x, y, z, w = Rotation.from_matrix(np.asarray(rotation, dtype=float)).as_quat()
    return float(x), float(y), float(z), float(w)


def time_ns(epoch: float, t: float) -> int:
    """Log time [ns]: the simulation time ``t`` [s] on the wire's clock (``epoch`` + t, UNIX)."""
    return int(round((float(epoch) + float(t)) * 1e9))


def jsonable(v: Any, depth: int = 0) -> Any:
    """A JSON-safe copy: numpy scalars and arrays to Python, NaN/inf to None, bytes left out."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, str):
        return v
    if depth > 4:
        return None
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist(), depth + 1)
    if isinstance(v, (list, tuple)):
        return [jsonable(x, depth + 1) for x in v]
    if isinstance(v, Mapping):
        return {str(k): jsonable(x, depth + 1) for k, x in v.items() if not isinstance(x, (bytes, bytearray))}
    return str(v)


class FanMapper:
    """Polar sonar samples -> a Cartesian fan image (apex at the bottom centre, range up).

    Built once per geometry (n_samples, n_beams, range window, azimuths); each frame is then
    one table lookup. height: [px] of the image; pixels outside the fan are 0."""

    def __init__(self, n_samples: int, azimuths: np.ndarray, range_min: float, range_max: float,
                 height: int = 400) -> None:
        az = np.asarray(azimuths, dtype=float).reshape(-1)
        nb = len(az)
        step = (az[-1] - az[0]) / (nb - 1) if nb > 1 else 0.02
        edges = np.concatenate([[az[0] - step / 2], (az[:-1] + az[1:]) / 2, [az[-1] + step / 2]])
        half = min(max(abs(edges[0]), abs(edges[-1])), math.pi / 2)
        scale = height / range_max                              # [px/m]
        width = max(2, int(math.ceil(2 * range_max * math.sin(half) * scale)) + 2)
        py, px = np.mgrid[0:height, 0:width]
        x = (px + 0.5 - width / 2) / scale                      # starboard [m]
        y = (height - py - 0.5) / scale                         # forward [m]
        r = np.hypot(x, y)
        th = np.arctan2(x, y)
        beam = np.searchsorted(edges, th, side="right") - 1
        row = np.floor((r - range_min) / (range_max - range_min) * n_samples).astype(np.int64)
        inside = (r >= range_min) & (r < range_max) & (beam >= 0) & (beam < nb) & (row >= 0) & (row < n_samples)
        self.index = np.where(inside, row * nb + np.clip(beam, 0, nb - 1), n_samples * nb)
        self.shape = (height, width)
        self.size = n_samples * nb

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(n_samples, n_beams) uint8 -> (height, width) uint8 fan."""
        flat = np.concatenate([np.asarray(image, dtype=np.uint8).reshape(-1), np.zeros(1, np.uint8)])
        return flat[self.index]


def fan_key(msg: Mapping[str, Any]) -> tuple[Any, ...]:
    img = msg["image"]
    az = np.asarray(msg["azimuths"], dtype=float)
    return (img.shape, float(msg["range_min"]), float(msg["range_max"]), float(az[0]), float(az[-1]), len(az))
