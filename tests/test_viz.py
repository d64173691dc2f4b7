"""Pictures: the fan's geometry checked against polar -> Cartesian computed here, and the files."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from hilsim import viz

NS, NB = 100, 32
RMIN, RMAX = 1.0, 11.0
HALF = math.radians(15.0)
# beam centres of 32 equal parts of [-15, +15] deg
AZ = -HALF + (np.arange(NB) + 0.5) * (2 * HALF / NB)


def cell_centre(i: int, j: int) -> tuple[float, float]:
    """(range [m], azimuth [rad]) of cell (sample i, beam j)."""
    return RMIN + (i + 0.5) * (RMAX - RMIN) / NS, float(AZ[j])


def expected_pixel(lay: viz.FanLayout, r: float, th: float) -> tuple[float, float]:
    """Apex at the bottom, range up, starboard right: x = r sin(th), y = r cos(th)."""
    return lay.apex[0] + r * math.sin(th) * lay.px_per_m, lay.apex[1] - r * math.cos(th) * lay.px_per_m


def bright_pixels(img: Image.Image, thresh: int = 128) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(img)[..., 0]
    ys, xs = np.nonzero(a >= thresh)
    return xs + 0.5, ys + 0.5


def test_layout_matches_the_drawn_fan():
    full = np.full((NS, NB), 255, np.uint8)
    img = viz.sonar_fan_image(full, AZ, RMIN, RMAX, size_px=400, labels=False, interpolation="nearest",
                              colormap="gray")
    lay = viz.fan_layout(AZ, RMIN, RMAX, size_px=400, labels=False)
    assert img.size == lay.size and img.height == 400
    xs, ys = bright_pixels(img)
    s, (ax, ay) = lay.px_per_m, lay.apex
    assert lay.theta_lo == pytest.approx(-HALF) and lay.theta_hi == pytest.approx(HALF)
    # extents of the fan, from the polar geometry
    assert abs(ys.min() - (ay - RMAX * s)) <= 1.0                       # top of the far arc (0 deg)
    assert abs(ys.max() - (ay - RMIN * math.cos(HALF) * s)) <= 1.0      # corners of the near arc
    assert abs(xs.min() - (ax - RMAX * math.sin(HALF) * s)) <= 1.0      # port corner of the far arc
    assert abs(xs.max() - (ax + RMAX * math.sin(HALF) * s)) <= 1.0      # starboard corner
    # the picture is just the fan: height = size_px spans the fan's vertical extent
    assert (RMAX - RMIN * math.cos(HALF)) * s == pytest.approx(400)
    # outside the fan: background
    assert tuple(np.asarray(img)[0, 0]) == viz.BACKGROUND


@pytest.mark.parametrize("interpolation", ["nearest", "bilinear"])
@pytest.mark.parametrize("i, j", [(70, 28), (20, 3), (50, 16)])
def test_bright_cell_lands_at_its_range_and_bearing(interpolation, i, j):
    sonar = np.zeros((NS, NB), np.uint8)
    sonar[i, j] = 255
    img = viz.sonar_fan_image(sonar, AZ, RMIN, RMAX, size_px=500, labels=False, interpolation=interpolation,
                              colormap="gray")
    lay = viz.fan_layout(AZ, RMIN, RMAX, size_px=500, labels=False)
    px, py = expected_pixel(lay, *cell_centre(i, j))
    blank = viz.sonar_fan_image(np.zeros_like(sonar), AZ, RMIN, RMAX, size_px=500, labels=False,
                                interpolation=interpolation, colormap="gray")
    a = np.asarray(img)[..., 0].astype(float) - np.asarray(blank)[..., 0]   # the cell alone
    ys, xs = np.nonzero(a > 0)
    w = a[ys, xs]
    cx, cy = (xs + 0.5) @ w / w.sum(), (ys + 0.5) @ w / w.sum()
    assert abs(cx - px) < 1.5 and abs(cy - py) < 1.5
    assert a[int(py), int(px)] >= (255 if interpolation == "nearest" else 150)
    # the cell's size: one beam wide and one bin tall (nearest); bilinear spreads to the neighbours
    if interpolation == "nearest":
        r, th = cell_centre(i, j)
        arc = r * (2 * HALF / NB) * lay.px_per_m
        depth = (RMAX - RMIN) / NS * lay.px_per_m
        assert abs((a > 0).sum() - arc * depth) <= 2 * (arc + depth) + 4


def test_starboard_is_right_and_range_increases_upward():
    sonar = np.zeros((NS, NB), np.uint8)
    sonar[:, AZ > 0] = 255                       # starboard half
    img = viz.sonar_fan_image(sonar, AZ, RMIN, RMAX, labels=False, colormap="gray")
    lay = viz.fan_layout(AZ, RMIN, RMAX, labels=False)
    xs, _ = bright_pixels(img)
    assert xs.min() >= lay.apex[0] - 1.0 and xs.size > 1000
    near, far = np.zeros((NS, NB), np.uint8), np.zeros((NS, NB), np.uint8)
    near[5, :], far[90, :] = 255, 255
    y_near = bright_pixels(viz.sonar_fan_image(near, AZ, RMIN, RMAX, labels=False, colormap="gray"))[1].mean()
    y_far = bright_pixels(viz.sonar_fan_image(far, AZ, RMIN, RMAX, labels=False, colormap="gray"))[1].mean()
    assert y_far < y_near                         # far ranges are higher in the picture


def test_labelled_fan_has_margins_and_the_same_geometry():
    sonar = np.zeros((NS, NB), np.uint8)
    sonar[70, 28] = 255
    img = viz.sonar_fan_image(sonar, AZ, RMIN, RMAX, size_px=300, colormap="gray")
    lay = viz.fan_layout(AZ, RMIN, RMAX, size_px=300, labels=True)
    bare = viz.fan_layout(AZ, RMIN, RMAX, size_px=300, labels=False)
    assert img.size == lay.size and lay.size[0] > bare.size[0] and lay.size[1] > bare.size[1]
    assert lay.px_per_m == pytest.approx(bare.px_per_m)
    px, py = expected_pixel(lay, *cell_centre(70, 28))
    patch = np.asarray(img)[int(py) - 1:int(py) + 2, int(px) - 1:int(px) + 2, 0]
    assert patch.max() > 200
    # grid and text are drawn: the labelled picture differs from the bare fan outside the cell
    assert len(np.unique(np.asarray(img).reshape(-1, 3), axis=0)) > 10


def test_fan_refuses_bad_input():
    with pytest.raises(ValueError):
        viz.sonar_fan_image(np.zeros((NS, NB), np.float32), AZ, RMIN, RMAX)   # type: ignore[arg-type]
    with pytest.raises(ValueError):
        viz.sonar_fan_image(np.zeros((NS, NB), np.uint8), AZ[::-1], RMIN, RMAX)
    with pytest.raises(ValueError):
        viz.sonar_fan_image(np.zeros((NS, NB), np.uint8), AZ[:-1], RMIN, RMAX)


def test_png_is_a_real_png_of_the_right_size(tmp_path):
    img = viz.sonar_fan_image(np.zeros((NS, NB), np.uint8), AZ, RMIN, RMAX, size_px=200)
    p = viz.save_png(img, tmp_path / "sub" / "fan.png")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(p) as back:
        assert back.format == "PNG" and back.size == img.size
        assert np.array_equal(np.asarray(back.convert("RGB")), np.asarray(img))


def test_raw_file_is_samples_by_beams_in_c_order(tmp_path):
    sonar = ((np.arange(NS)[:, None] * 7 + np.arange(NB)[None, :] * 3) % 251).astype(np.uint8)
    p = viz.save_raw(sonar, tmp_path / "frame.raw")
    data = p.read_bytes()
    assert len(data) == NS * NB
    for sample, beam in [(0, 0), (0, NB - 1), (1, 0), (NS - 1, 5), (37, 19)]:
        assert data[sample * NB + beam] == (sample * 7 + beam * 3) % 251
    with pytest.raises(ValueError):
        viz.save_raw(sonar.astype(np.int16), tmp_path / "bad.raw")


def test_camera_and_depth_images():
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    assert np.array_equal(np.asarray(viz.camera_image(rgb)), rgb)
    depth = np.tile(np.linspace(1.0, 5.0, 64, dtype=np.float32), (48, 1))
    depth[:5, :5] = np.inf
    grey = np.asarray(viz.depth_image(depth, colormap="gray"))
    assert grey.shape == (48, 64, 3)
    assert np.all(grey[:5, :5] == 0)                               # nothing hit: black
    assert grey[20, 10, 0] > grey[20, 40, 0] > grey[20, 63, 0]      # nearer is brighter
    assert tuple(grey[20, 63]) == (0, 0, 0) and tuple(grey[20, 0]) == (255, 255, 255)
    colour = np.asarray(viz.depth_image(depth, near=0.0, far=10.0))
    assert np.all(colour[:5, :5] == 0) and not np.array_equal(colour[20, 10], colour[20, 60])


def test_figure_puts_one_column_per_position_fan_above_camera():
    fan = Image.new("RGB", (200, 300), (10, 200, 10))
    cams = [Image.new("RGB", (160, 120), c) for c in ((200, 0, 0), (0, 0, 200), (200, 200, 0))]
    fig = viz.figure_positions([(lab, fan, cam) for lab, cam in zip("ABC", cams)], column_width=100)
    arr = np.asarray(fig)
    gap, label_h = 12, 26
    fan_h, cam_h = 150, 75                        # scaled to 100 px wide
    assert fig.size == (gap + 3 * (100 + gap), label_h + fan_h + gap + cam_h + gap)
    for k, cam in enumerate(cams):
        x = gap + k * (100 + gap) + 50
        assert tuple(arr[label_h + fan_h // 2, x]) == (10, 200, 10)            # fan on top
        assert tuple(arr[label_h + fan_h + gap + cam_h // 2, x]) == cam.getpixel((0, 0))  # camera below
        assert np.any(arr[:label_h, x - 20:x + 20] < 128)                      # the label is drawn
    with pytest.raises(ValueError):
        viz.figure_positions([])
