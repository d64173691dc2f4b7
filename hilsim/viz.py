"""Pictures from plain arrays: the sonar fan, camera and depth images, the paper's Fig. 4.

Pure picture-making with Pillow (headless, no pyplot); nothing here knows about
the simulator's objects, only arrays and SI numbers.

Sonar fan geometry (:func:`sonar_fan_image`)
--------------------------------------------
The sonar image is (n_samples, n_beams): row i is range bin i, covering
``[range_min + i dr, range_min + (i + 1) dr)`` with ``dr = (range_max - range_min)
/ n_samples``; column j is the beam at ``azimuths[j]`` [rad], ascending (beam 0
port, positive azimuth starboard), each beam owning the wedge up to half-way to
its neighbours (the outer beams as wide as their inner halves). The fan is drawn
in Cartesian space like a sonar display: the apex at the bottom, range
increasing upward, starboard to the right. A point at range r and azimuth theta
is at ``x = r sin(theta)`` (right) and ``y = r cos(theta)`` (up) [m] from the
apex; with the layout's ``px_per_m`` and ``apex`` (pixel coordinates, the
centre of pixel (i, j) at (i + 0.5, j + 0.5)) it lands at
``(apex_x + x px_per_m, apex_y - y px_per_m)``. Every output pixel looks its
(range, bearing) up in the image (nearest cell, or bilinear between cell
centres); the lookup table is built once per geometry and cached.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from PIL import Image, ImageDraw, ImageFont

U8 = NDArray[np.uint8]
F64 = NDArray[np.float64]

BACKGROUND = (22, 26, 34)          # outside the fan
GRID = (150, 160, 170)             # range rings and bearing lines
TEXT = (230, 232, 235)


# ---- colour maps ---------------------------------------------------------------------------

def _ramp(stops: Sequence[tuple[float, tuple[int, int, int]]]) -> U8:
    """(256, 3) uint8 colour table interpolated linearly between (position in [0, 1], rgb) stops."""
    x = np.linspace(0.0, 1.0, 256)
    pos = [s[0] for s in stops]
    out = np.stack([np.interp(x, pos, [s[1][c] for s in stops]) for c in range(3)], axis=1)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


COLORMAPS: dict[str, U8] = {
    "gray": np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1),
    # black -> dark red -> orange -> pale yellow: the look of many sonar displays
    "sonar": _ramp([(0.0, (0, 0, 0)), (0.35, (120, 30, 5)), (0.7, (240, 150, 30)), (1.0, (255, 250, 210))]),
    # near = warm, far = cool, for depth images
    "depth": _ramp([(0.0, (255, 245, 150)), (0.25, (250, 150, 40)), (0.5, (200, 40, 80)),
                    (0.75, (90, 30, 150)), (1.0, (20, 20, 90))]),
}


def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):                 # Pillow without FreeType: the bitmap font
        return ImageFont.load_default()


# ---- sonar fan -----------------------------------------------------------------------------

@dataclass(frozen=True)
class FanLayout:
    """Where the fan sits in the picture.

    size: (width, height) [px] of the whole picture; apex: (x, y) continuous
    pixel coordinates of the fan's apex (range 0); px_per_m: scale [px/m];
    theta_lo, theta_hi: [rad] outer edges of the fan; range_min, range_max [m].
    """

    size: tuple[int, int]
    apex: tuple[float, float]
    px_per_m: float
    theta_lo: float
    theta_hi: float
    range_min: float
    range_max: float

    def to_pixel(self, rng: F64, azimuth: F64) -> F64:
        """(n, 2) pixel coordinates (x right, y down) of (n,) ranges [m] and azimuths [rad]."""
        r, th = np.asarray(rng, dtype=float), np.asarray(azimuth, dtype=float)
        return np.stack([self.apex[0] + r * np.sin(th) * self.px_per_m,
                         self.apex[1] - r * np.cos(th) * self.px_per_m], axis=-1)


@dataclass(frozen=True)
class _FanTable:
    layout: FanLayout
    inside: NDArray[np.intp]                 # flat output pixel indices inside the fan
    idx: tuple[NDArray[np.intp], ...]        # flat image indices, 1 (nearest) or 4 (bilinear)
    weights: tuple[NDArray[np.float32], ...]  # matching weights (bilinear)
    overlay: tuple[NDArray[np.intp], U8, NDArray[np.float32]]  # pixels, rgb, alpha of grid + labels


def _nice_step(span: float, target: int, steps: Sequence[float]) -> float:
    """The step from ``steps`` x 10^k giving close to ``target`` divisions of ``span``."""
    best, best_err = steps[0], math.inf
    for k in range(-3, 5):
        for s in steps:
            step = s * 10.0 ** k
            err = abs(span / step - target)
            if err < best_err:
                best, best_err = step, err
    return best


def _beam_edges(az: F64, beam_width: float | None) -> tuple[float, float]:
    if az.size == 1:
        if beam_width is None:
            raise ValueError("a single beam needs beam_width [rad]")
        return float(az[0] - beam_width / 2), float(az[0] + beam_width / 2)
    return float(az[0] - (az[1] - az[0]) / 2), float(az[-1] + (az[-1] - az[-2]) / 2)


def fan_layout(azimuths: F64, range_min: float, range_max: float, *, size_px: int = 480,
               labels: bool = True, beam_width: float | None = None) -> FanLayout:
    """The picture geometry :func:`sonar_fan_image` uses (see the module docstring).

    azimuths: (n_beams,) [rad] ascending; range_min < range_max [m]; size_px:
    height [px] of the fan itself (its vertical extent); labels: leave margins
    for the title and the ring and bearing labels; beam_width [rad]: only needed
    for a single beam.
    """
    az = np.asarray(azimuths, dtype=float)
    if az.ndim != 1 or az.size == 0 or np.any(np.diff(az) <= 0):
        raise ValueError("azimuths must be a non-empty ascending (n_beams,) array [rad]")
    if not 0.0 <= range_min < range_max:
        raise ValueError(f"need 0 <= range_min < range_max, got {range_min}, {range_max}")
    lo, hi = _beam_edges(az, beam_width)
    th = np.linspace(lo, hi, 721)
    x = np.concatenate([range_min * np.sin(th), range_max * np.sin(th)])
    y = np.concatenate([range_min * np.cos(th), range_max * np.cos(th)])
    if lo < 0.0 < hi:                          # the top of the far arc
        x, y = np.append(x, 0.0), np.append(y, range_max)
    x_lo, x_hi, y_lo, y_hi = x.min(), x.max(), y.min(), y.max()
    scale = size_px / (y_hi - y_lo)
    left, right, top, bottom = (64, 64, 44, 10) if labels else (0, 0, 0, 0)
    width = int(math.ceil((x_hi - x_lo) * scale)) + left + right
    height = int(size_px) + top + bottom
    return FanLayout(size=(width, height), apex=(left - x_lo * scale, top + y_hi * scale), px_per_m=scale,
                     theta_lo=lo, theta_hi=hi, range_min=float(range_min), range_max=float(range_max))


@functools.lru_cache(maxsize=16)
def _fan_table(n_samples: int, az_key: tuple[float, ...], range_min: float, range_max: float, size_px: int,
               labels: bool, interpolation: str, beam_width: float | None, title: str) -> _FanTable:
    az = np.asarray(az_key, dtype=float)
    nb = az.size
    lay = fan_layout(az, range_min, range_max, size_px=size_px, labels=labels, beam_width=beam_width)
    w, h = lay.size
    px = (np.arange(w) + 0.5 - lay.apex[0]) / lay.px_per_m
    py = (lay.apex[1] - (np.arange(h) + 0.5)) / lay.px_per_m
    x, y = np.meshgrid(px, py)
    r = np.hypot(x, y)
    th = np.arctan2(x, y)
    ok = (r >= range_min) & (r < range_max) & (th >= lay.theta_lo) & (th <= lay.theta_hi)
    inside = np.flatnonzero(ok.ravel())
    r, th = r.ravel()[inside], th.ravel()[inside]
    dr = (range_max - range_min) / n_samples
    fs = (r - range_min) / dr                                  # range in bins
    if interpolation == "nearest":
        i = np.minimum(fs.astype(np.intp), n_samples - 1)
        mid = (az[1:] + az[:-1]) / 2.0
        j = np.searchsorted(mid, th).astype(np.intp)
        idx: tuple[NDArray[np.intp], ...] = (i * nb + j,)
        weights: tuple[NDArray[np.float32], ...] = ()
    elif interpolation == "bilinear":
        fr = np.clip(fs - 0.5, 0.0, n_samples - 1)             # between bin centres
        i0 = np.minimum(fr.astype(np.intp), max(n_samples - 2, 0))
        i1 = np.minimum(i0 + 1, n_samples - 1)
        wr = fr - i0
        fb = np.interp(th, az, np.arange(nb, dtype=float)) if nb > 1 else np.zeros_like(th)
        j0 = np.minimum(fb.astype(np.intp), max(nb - 2, 0))
        j1 = np.minimum(j0 + 1, nb - 1)
        wb = fb - j0
        idx = (i0 * nb + j0, i0 * nb + j1, i1 * nb + j0, i1 * nb + j1)
        weights = tuple(np.asarray(v, dtype=np.float32) for v in
                        ((1 - wr) * (1 - wb), (1 - wr) * wb, wr * (1 - wb), wr * wb))
    else:
        raise ValueError(f"interpolation must be 'nearest' or 'bilinear', got {interpolation!r}")
    return _FanTable(lay, inside, idx, weights, _fan_overlay(lay, labels, title))


def _fan_overlay(lay: FanLayout, labels: bool, title: str) -> tuple[NDArray[np.intp], U8, NDArray[np.float32]]:
    """Range rings, bearing lines and their labels, drawn once: (pixels, rgb, alpha)."""
    w, h = lay.size
    if not labels:
        return np.zeros(0, np.intp), np.zeros((0, 3), np.uint8), np.zeros(0, np.float32)
    img = Image.new("RGBA", (w, h), (0, 0, 0, 0))
    dr_ = ImageDraw.Draw(img)
    font = _font(11)
    grid = GRID + (150,)
    ax, ay, s = lay.apex[0], lay.apex[1], lay.px_per_m
    rmin, rmax = lay.range_min, lay.range_max

    def pt(r: float, t: float) -> tuple[float, float]:
        return ax + r * math.sin(t) * s, ay - r * math.cos(t) * s

    # range rings at a round step, labelled in metres just outside the starboard edge
    step = _nice_step(rmax - rmin, 5, (1.0, 2.0, 2.5, 5.0))
    first = math.ceil(rmin / step - 1e-9) * step
    rings = [float(k) for k in np.arange(first, rmax + 1e-9, step) if k > 1e-9]
    a0, a1 = math.degrees(lay.theta_lo) - 90.0, math.degrees(lay.theta_hi) - 90.0  # PIL: 0 deg = +x, clockwise
    for rr in rings:
        rad = rr * s
        dr_.arc([ax - rad, ay - rad, ax + rad, ay + rad], a0, a1, fill=grid, width=1)
        x, y = pt(rr, lay.theta_hi)
        dr_.text((x + 4, y), f"{rr:g} m", fill=TEXT + (255,), font=font, anchor="lm")
    # bearing lines at a round number of degrees, labelled above the far arc
    span = math.degrees(lay.theta_hi - lay.theta_lo)
    bstep = _nice_step(span, 4, (1.0, 2.0, 5.0, 10.0, 15.0, 30.0, 45.0))
    b = math.ceil(math.degrees(lay.theta_lo) / bstep - 1e-9) * bstep
    while b <= math.degrees(lay.theta_hi) + 1e-9:
        t = math.radians(b)
        dr_.line([pt(rmin, t), pt(rmax, t)], fill=grid, width=1)
        x, y = pt(rmax + 10.0 / s, t)
        dr_.text((x, y), f"{b:g}°", fill=TEXT + (255,), font=font, anchor="mm")
        b += bstep
    # the fan's outline
    for t in (lay.theta_lo, lay.theta_hi):
        dr_.line([pt(rmin, t), pt(rmax, t)], fill=GRID + (220,), width=1)
    for rr in (rmin, rmax):
        if rr > 0:
            dr_.arc([ax - rr * s, ay - rr * s, ax + rr * s, ay + rr * s], a0, a1, fill=GRID + (220,), width=1)
    dr_.text((w / 2, 4), title, fill=TEXT + (255,), font=_font(12), anchor="ma")
    a = np.asarray(img)
    alpha = a[..., 3].ravel()
    pix = np.flatnonzero(alpha)
    return pix, a[..., :3].reshape(-1, 3)[pix].copy(), (alpha[pix] / 255.0).astype(np.float32)


def sonar_fan_image(image: U8, azimuths: F64, range_min: float, range_max: float, *, size_px: int = 480,
                    labels: bool = True, interpolation: str = "bilinear", colormap: str = "sonar",
                    title: str | None = None, beam_width: float | None = None) -> Image.Image:
    """The sonar frame as a fan (Cartesian display), as a PIL RGB image.

    image: (n_samples, n_beams) uint8, row = range bin (nearest first), column =
    beam; azimuths: (n_beams,) [rad] ascending, beam 0 port, positive =
    starboard = right of the picture; range_min, range_max: [m] the window the
    rows span; size_px: height of the fan [px] (the width follows from the
    geometry); labels: range rings [m], bearing lines [deg] and a title line;
    interpolation: ``"nearest"`` or ``"bilinear"``; colormap: a key of
    :data:`COLORMAPS`; beam_width [rad]: only for a single beam. Pixels outside
    the fan are :data:`BACKGROUND`. Geometry: see the module docstring and
    :func:`fan_layout` (the same layout).
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"image must be a (n_samples, n_beams) uint8 array, got {img.dtype} {img.shape}")
    az = np.asarray(azimuths, dtype=float)
    if az.shape != (img.shape[1],):
        raise ValueError(f"azimuths has shape {az.shape}, expected ({img.shape[1]},) for {img.shape[1]} beams")
    if colormap not in COLORMAPS:
        raise ValueError(f"unknown colormap {colormap!r}; choose from {', '.join(COLORMAPS)}")
    if title is None:
        lo, hi = _beam_edges(az, beam_width)
        title = (f"sonar: {img.shape[1]} beams x {img.shape[0]} samples, "
                 f"{range_min:g}-{range_max:g} m, {math.degrees(hi - lo):.1f} deg")
    tb = _fan_table(img.shape[0], tuple(az.tolist()), float(range_min), float(range_max), int(size_px),
                    bool(labels), interpolation, beam_width, title)
    w, h = tb.layout.size
    flat = img.ravel()
    if tb.weights:
        val = np.zeros(tb.inside.size, dtype=np.float32)
        for ix, wt in zip(tb.idx, tb.weights):
            val += np.take(flat, ix).astype(np.float32) * wt
        level = np.clip(val + 0.5, 0, 255).astype(np.uint8)
    else:
        level = np.take(flat, tb.idx[0])
    out = np.empty((h * w, 3), dtype=np.uint8)
    out[:] = BACKGROUND
    out[tb.inside] = np.take(COLORMAPS[colormap], level, axis=0)
    pix, rgb, alpha = tb.overlay
    if pix.size:
        base = out[pix].astype(np.float32)
        out[pix] = (base + (rgb.astype(np.float32) - base) * alpha[:, None] + 0.5).astype(np.uint8)
    return Image.fromarray(out.reshape(h, w, 3), "RGB")


# ---- camera and depth --------------------------------------------------------------------

def camera_image(rgb: U8) -> Image.Image:
    """A camera frame's (h, w, 3) uint8 RGB array as a PIL image (the pixels unchanged)."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"rgb must be (h, w, 3) uint8, got {a.dtype} {a.shape}")
    return Image.fromarray(np.ascontiguousarray(a), "RGB")


def depth_image(depth: NDArray[np.floating], *, near: float | None = None, far: float | None = None,
                colormap: str = "depth") -> Image.Image:
    """(h, w) depth [m] as a false-colour (or ``colormap="gray"``) PIL RGB image.

    near, far [m]: the distances mapped to the two ends of the colour map
    (default: the smallest and largest finite depth); near is bright/warm.
    Pixels where nothing is hit (inf or NaN) are black.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (h, w), got {d.shape}")
    finite = np.isfinite(d)
    lo = near if near is not None else (float(d[finite].min()) if finite.any() else 0.0)
    hi = far if far is not None else (float(d[finite].max()) if finite.any() else 1.0)
    span = hi - lo if hi > lo else 1.0
    x = np.clip((np.where(finite, d, hi) - lo) / span, 0.0, 1.0)
    lut = COLORMAPS[colormap]
    if colormap == "gray":
        lut = lut[::-1]                             # near white, far dark
    out = np.take(lut, (x * 255.0 + 0.5).astype(np.intp), axis=0)
    out[~finite] = 0
    return Image.fromarray(out.astype(np.uint8), "RGB")


# ---- the paper's Fig. 4 ----------------------------------------------------------------------

def figure_positions(panels: Sequence[tuple[str, Image.Image, Image.Image]], *, column_width: int = 320,
                     title: str | None = None) -> Image.Image:
    """A side-by-side figure like the paper's Fig. 4: one column per position.

    panels: [(label, fan image, camera image), ...] (e.g. A, B, C); each column
    shows the label, the sonar fan above and the camera image below, both
    scaled to ``column_width`` [px] keeping their aspect ratio. White background.
    """
    if not panels:
        raise ValueError("figure_positions needs at least one panel")
    gap, label_h = 12, 26
    title_h = 28 if title else 0

    def fit(im: Image.Image) -> Image.Image:
        hgt = max(1, round(im.height * column_width / im.width))
        return im.convert("RGB").resize((column_width, hgt), Image.Resampling.LANCZOS)

    cols = [(lab, fit(fan), fit(cam)) for lab, fan, cam in panels]
    fan_h = max(f.height for _, f, _ in cols)
    cam_h = max(c.height for _, _, c in cols)
    width = gap + len(cols) * (column_width + gap)
    height = title_h + label_h + fan_h + gap + cam_h + gap
    fig = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(fig)
    if title:
        draw.text((width / 2, 6), title, fill=(0, 0, 0), font=_font(16), anchor="ma")
    for k, (lab, fan, cam) in enumerate(cols):
        x = gap + k * (column_width + gap)
        draw.text((x + column_width / 2, title_h + label_h / 2), lab, fill=(0, 0, 0), font=_font(18),
                  anchor="mm")
        fig.paste(fan, (x, title_h + label_h + (fan_h - fan.height)))
        fig.paste(cam, (x, title_h + label_h + fan_h + gap))
    return fig


# ---- files ---------------------------------------------------------------------------------

def save_png(img: Image.Image, path: str | Path) -> Path:
    """Write ``img`` as a PNG (creating the parent folder); returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    img.save(p, format="PNG")
    return p


def save_raw(array: U8, path: str | Path) -> Path:
    """Write a uint8 array's bytes in C order, no header; returns the path.

    For a sonar image (n_samples, n_beams) that is range sample by range sample,
    beam index fastest: byte ``sample * n_beams + beam`` (beam 0 port), the file
    ``n_samples * n_beams`` bytes long. Read back with
    ``np.fromfile(path, np.uint8).reshape(n_samples, n_beams)``.
    """
    a = np.asarray(array)
    if a.dtype != np.uint8:
        raise ValueError(f"save_raw writes uint8 arrays, got {a.dtype}")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(np.ascontiguousarray(a).tobytes(order="C"))
    return p
