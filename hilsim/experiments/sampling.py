"""The paper's 96 x 1000 sampling against the artifact-free one: where range bins stay empty.

The paper casts 96 x 1000 rays and puts each ray's echo in the one range bin
of its hit ("circular patterns" in its Fig. 4: bins no ray lands in stay
black). hilsim spreads each echo over the range interval its elevation step
covers (:mod:`hilsim.sim.sonar`). Both are rendered here from the same pose
with the same rays and the paper's relative gain, realism off, so that only
the sampling differs.

Empty bins are counted inside the *footprint*: the (range bin, beam) cells a
surface really covers. Within one beam, two rays adjacent in elevation that
hit the same face (same object, same facet direction) bound a continuous
strip of that face, so every bin between their two ranges holds surface; the
footprint is the union of those spans. A footprint cell with zero echo
intensity is an empty bin. Shadows and gaps between objects lie between rays
on *different* faces and are not counted.

At the paper's geometry (45 deg tilt, 1.2 m above the floor) adjacent rays
land under 1 mm apart in range (0.4 mm median), far less than a 9.8 mm bin
(512 samples over 5 m), so the paper's sampling leaves no empty bins there. The gaps appear
where ``|dR/dphi| dphi`` exceeds a bin: at grazing incidence and with finer
bins. :data:`VARIANTS` lists such geometries, mildest first; the experiment
uses the first in which the paper's sampling does leave empty bins, and says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image, ImageDraw, ImageFont

from hilsim import viz
from hilsim.sim.geometry import Pose, rpy_to_matrix
from hilsim.sim.sonar import ImagingSonar, SonarFrame
from hilsim.sim.sonar_profile import SonarSettings
from hilsim.sim.world import World

PAPER_ELEVATION_RAYS = 1000  # the paper's rays per beam in elevation (section 2.2)


@dataclass(frozen=True)
class SamplingCase:
    """A sonar geometry to compare the samplings in.

    key: short name; label: what it is, for figures; tilt_deg: the sonar's
    downward tilt [deg] (None: as mounted); n_samples: range bins (None: the profile's).
    """

    key: str
    label: str
    tilt_deg: float | None = None
    n_samples: int | None = None


AS_MOUNTED = SamplingCase("experiment", "as in the experiment")
VARIANTS = (
    SamplingCase("tilt10", "variant: sonar tilted 10 deg down", tilt_deg=10.0),
    SamplingCase("bins2048", "variant: 2048 range bins", n_samples=2048),
    SamplingCase("tilt10_bins2048", "variant: tilted 10 deg down, 2048 range bins", tilt_deg=10.0, n_samples=2048),
)


def case_mount(case: SamplingCase, mount: Pose) -> Pose:
    """The sensor mount (sensor -> body) of ``case``: ``mount`` with its pitch set to -tilt."""
    if case.tilt_deg is None:
        return mount
    roll, _, yaw = mount.rpy()
    return Pose(np.asarray(mount.position, dtype=float), rpy_to_matrix(roll, -math.radians(case.tilt_deg), yaw))


def case_settings(case: SamplingCase, base: SonarSettings) -> tuple[SonarSettings, SonarSettings]:
    """(paper, artifact-free) settings: the paper's model (1000 rays per beam, no
    spreading, relative gain, realism off) and the same with spreading on."""
    paper = base.paper_model().replace(elevation_rays=PAPER_ELEVATION_RAYS,
                                       n_samples=case.n_samples or base.n_samples)
    return paper, paper.replace(spread=True)


def footprint(world: World, sonar: ImagingSonar, pose: Pose,
              settings: SonarSettings) -> tuple[NDArray[np.bool_], tuple[float, float]]:
    """(n_samples, n_beams) bool: the cells surfaces cover (see the module doc), and the
    (median, max) range step [m] between rays adjacent in elevation on the same face."""
    dirs_s, _ = sonar.rays(settings)
    nb, ne, ns = sonar.profile.n_beams, settings.elevation_rays, settings.n_samples
    dirs = dirs_s @ np.asarray(pose.rotation, dtype=float).T
    hits = world.cast(np.broadcast_to(np.asarray(pose.position, dtype=float), dirs.shape), dirs,
                      t_min=settings.range_min, t_max=settings.range_max)
    hit = hits.tri >= 0
    tri = np.where(hit, hits.tri, 0)
    face = np.where(hit, world.tri_object[tri] * 6 + world.tri_facet[tri], -1).reshape(nb, ne)
    rng = np.where(hit, hits.t, settings.range_min).reshape(nb, ne)
    row = np.clip((rng - settings.range_min) / settings.range_resolution, 0, ns - 1).astype(np.int64)
    pair = (face[:, :-1] >= 0) & (face[:, :-1] == face[:, 1:])
    step = np.abs(np.diff(rng, axis=1))[pair]
    spacing = (float(np.median(step)), float(step.max())) if step.size else (0.0, 0.0)
    lo = np.minimum(row[:, :-1], row[:, 1:])[pair]
    hi = np.maximum(row[:, :-1], row[:, 1:])[pair]
    beam = np.broadcast_to(np.arange(nb)[:, None], pair.shape)[pair]
    # +1 where a span opens, -1 one row after it closes; a running sum down each beam
    edges = (np.bincount(lo * nb + beam, minlength=(ns + 1) * nb)
             - np.bincount((hi + 1) * nb + beam, minlength=(ns + 1) * nb))
    return np.cumsum(edges.reshape(ns + 1, nb), axis=0)[:ns] > 0, spacing


@dataclass(frozen=True)
class SamplingResult:
    """The two samplings of one case at one pose, and the footprint they share."""

    case: SamplingCase
    paper: SonarFrame
    free: SonarFrame
    footprint: NDArray[np.bool_]
    ray_spacing: tuple[float, float]  # [m] (median, max) range step between adjacent rays on one face

    def empty(self, frame: SonarFrame) -> NDArray[np.bool_]:
        """(n_samples, n_beams) footprint cells without any echo in ``frame``."""
        return self.footprint & (frame.intensity <= 0.0)

    @property
    def empty_paper(self) -> int:
        return int(np.count_nonzero(self.empty(self.paper)))

    @property
    def empty_free(self) -> int:
        return int(np.count_nonzero(self.empty(self.free)))

    def summary(self) -> dict[str, Any]:
        s = self.paper.settings
        return {"case": self.case.key, "label": self.case.label,
                "tilt_deg": round(-math.degrees(self.paper.pose.rpy()[1]), 4),
                "n_samples": s.n_samples, "range_bin_m": s.range_resolution,
                "elevation_rays": s.elevation_rays,
                "ray_spacing_m": {"median": self.ray_spacing[0], "max": self.ray_spacing[1]},
                "footprint_bins": int(np.count_nonzero(self.footprint)),
                "empty_bins": {"paper_96x1000": self.empty_paper, "artifact_free": self.empty_free}}


def compare(world: World, sonar: ImagingSonar, body: Pose, mount: Pose, case: SamplingCase,
            frame_index: int = 0) -> SamplingResult:
    """Render ``case`` from the vehicle pose ``body`` (body -> world) both ways."""
    pose = body @ case_mount(case, mount)
    paper, free = case_settings(case, sonar.profile.default_settings())
    mask, spacing = footprint(world, sonar, pose, paper)
    return SamplingResult(case, sonar.render(world, pose, paper, frame_index=frame_index),
                          sonar.render(world, pose, free, frame_index=frame_index), mask, spacing)


def choose_variant(world: World, sonar: ImagingSonar, body: Pose, mount: Pose) -> SamplingCase | None:
    """The first of :data:`VARIANTS` in which the paper's sampling leaves empty bins at ``body``."""
    for case in VARIANTS:
        if compare(world, sonar, body, mount, case).empty_paper > 0:
            return case
    return None


# ---- the figure ------------------------------------------------------------------------------

def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # Pillow without FreeType
        return ImageFont.load_default()


def _fan(frame: SonarFrame, image: NDArray[np.uint8], title: str, size_px: int, colormap: str = "sonar") -> Image.Image:
    # nearest cell per display pixel, as a display does: an empty bin stays black
    return viz.sonar_fan_image(image, frame.azimuths, frame.range_min, frame.range_max, size_px=size_px,
                               interpolation="nearest", title=title, colormap=colormap)


def result_panels(label: str, res: SamplingResult, size_px: int, mask: bool) -> list[tuple[Image.Image, str]]:
    """Fans of one result: paper, artifact-free (and, with ``mask``, the paper's empty bins)."""
    fp = int(np.count_nonzero(res.footprint))
    out = [(_fan(res.paper, res.paper.image, f"{label}: paper 96 x 1000", size_px),
            f"empty bins {res.empty_paper} of {fp}"),
           (_fan(res.free, res.free.image, f"{label}: artifact-free", size_px),
            f"empty bins {res.empty_free} of {fp}")]
    if mask:
        m = np.where(res.empty(res.paper), 255, np.where(res.footprint, 60, 0)).astype(np.uint8)
        out.append((_fan(res.paper, m, f"{label}: paper's empty bins", size_px, "gray"),
                    "white: empty, grey: echo"))
    return out


def grid_figure(rows: Sequence[tuple[str, Sequence[tuple[Image.Image, str]]]], headers: Sequence[str],
                title: str, notes: Sequence[str] = ()) -> Image.Image:
    """Panels in a grid: a row label at the left, a header over each column and
    a caption under each panel; ``notes`` are lines under the title."""
    gap, label_w, head_h, cap_h = 10, 36, 34, 22
    col_w = max(p.width for _, ps in rows for p, _ in ps)
    row_h = max(p.height for _, ps in rows for p, _ in ps) + cap_h
    top = 30 + 18 * len(notes) + head_h
    n_cols = max(len(ps) for _, ps in rows)
    fig = Image.new("RGB", (label_w + n_cols * (col_w + gap) + gap, top + len(rows) * (row_h + gap)),
                    (255, 255, 255))
    draw = ImageDraw.Draw(fig)
    draw.text((fig.width / 2, 6), title, fill=(0, 0, 0), font=_font(16), anchor="ma")
    for i, line in enumerate(notes):
        draw.text((fig.width / 2, 28 + 18 * i), line, fill=(60, 60, 60), font=_font(13), anchor="ma")
    for c, head in enumerate(headers):
        x = label_w + gap + c * (col_w + gap) + col_w / 2
        for k, part in enumerate(head.split("\n")):
            draw.text((x, top - head_h + 2 + 15 * k), part, fill=(0, 0, 0), font=_font(13), anchor="ma")
    for r, (lab, panels) in enumerate(rows):
        y = top + r * (row_h + gap)
        draw.text((label_w / 2, y + row_h / 2), lab, fill=(0, 0, 0), font=_font(20), anchor="mm")
        for c, (img, cap) in enumerate(panels):
            x = label_w + gap + c * (col_w + gap)
            fig.paste(img, (x + (col_w - img.width) // 2, y))
            draw.text((x + col_w / 2, y + row_h - cap_h + 4), cap, fill=(0, 0, 0), font=_font(13), anchor="ma")
    return fig
