"""The imaging-sonar model against geometry and physics computed here, independently.

Scenes are built from trimesh boxes. The sensor sits at the world origin
unless stated; with pose identity its boresight is world +x (north), +y is
starboard (east), +z down. Expected values are derived in the tests from the
documented ray layout (beam and elevation-ray centres of equal parts of the
apertures) and eq. 9, never read back from the model.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from hilsim.config import ConfigError
from hilsim.sim.geometry import Pose
from hilsim.sim.sonar import (
    ImagingSonar,
    SonarProfile,
    SonarSettings,
    beam_pattern_matrix,
    load_sonar_profile,
    pure_water_absorption,
    spread_deposit,
)
from hilsim.sim.state import VehicleState
from hilsim.sim.world import Material, Water, World, WorldObject

ROOT = Path(__file__).resolve().parents[2]
HF = ROOT / "devices" / "sonars" / "didson_hf.toml"
LF = ROOT / "devices" / "sonars" / "didson_lf.toml"

Z0 = 1.5e6
CONCRETE = Material("concrete", 8.0e6)
PLASTIC = Material("plastic", 3.5e6)


@pytest.fixture(scope="module")
def hf() -> SonarProfile:
    return load_sonar_profile(HF)


def quiet(profile: SonarProfile, **changes: object) -> SonarSettings:
    """Deterministic settings: realism off, TVG off, fixed gain, spreading on."""
    return profile.default_settings().realism_off().replace(tvg=False, **changes)


def floor_world(altitude: float, material: Material = CONCRETE) -> World:
    """A 40 m x 40 m slab whose top face lies ``altitude`` below the origin."""
    slab = trimesh.creation.box(extents=(40.0, 40.0, 0.1))
    slab.apply_translation((0.0, 0.0, altitude + 0.05))
    return World([WorldObject("floor", slab, material)], Water(impedance=Z0))


def wall(distance: float, yaw: float = 0.0, through: tuple[float, float] | None = None) -> trimesh.Trimesh:
    """A 10 m x 10 m plate whose front face (normal toward the sensor) passes through
    ``through`` (x, y) (default (distance, 0)) and is turned by ``yaw`` [rad] about z."""
    plate = trimesh.creation.box(extents=(0.05, 10.0, 10.0))
    plate.apply_translation((0.025, 0.0, 0.0))  # front face at x = 0, normal -x
    plate.apply_transform(trimesh.transformations.rotation_matrix(yaw, (0.0, 0.0, 1.0)))
    x, y = through if through is not None else (distance, 0.0)
    plate.apply_translation((x, y, 0.0))
    return plate


def wall_world(distance: float, material: Material = CONCRETE, yaw: float = 0.0,
               through: tuple[float, float] | None = None) -> World:
    return World([WorldObject("wall", wall(distance, yaw, through), material)], Water(impedance=Z0))


def beam_azimuths(profile: SonarProfile) -> np.ndarray:
    lo, hi = profile.azimuth_limits
    return lo + (np.arange(profile.n_beams) + 0.5) * (hi - lo) / profile.n_beams


def elevations(profile: SonarProfile, n: int) -> np.ndarray:
    lo, hi = profile.elevation_limits
    return lo + (np.arange(n) + 0.5) * (hi - lo) / n


def pitched_down(tilt_deg: float) -> Pose:
    return Pose.from_xyz_rpy((0.0, 0.0, 0.0), (0.0, -math.radians(tilt_deg), 0.0))


def down_component(theta: float, phi: float, tilt: float) -> float:
    """World z (down) of the ray (theta, phi) of a sensor pitched ``tilt`` [rad] down.

    Sensor ray (cos phi cos theta, cos phi sin theta, -sin phi); a nose-down
    pitch by ``tilt`` turns x toward +z: z_w = sin(tilt) x + cos(tilt) z.
    """
    x = math.cos(phi) * math.cos(theta)
    z = -math.sin(phi)
    return math.sin(tilt) * x + math.cos(tilt) * z


# ------------------------------------------------------------ conventions


def test_ray_layout_and_beam_order(hf: SonarProfile) -> None:
    son = ImagingSonar(hf, quiet(hf, elevation_rays=7))
    dirs, beam = son.rays()
    th = np.repeat(beam_azimuths(hf), 7)
    ph = np.tile(elevations(hf, 7), 96)
    want = np.stack([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), -np.sin(ph)], axis=1)
    np.testing.assert_allclose(dirs, want, atol=1e-15)
    np.testing.assert_array_equal(beam, np.repeat(np.arange(96), 7))
    assert np.all(np.diff(son.azimuths) > 0) and son.azimuths[0] < 0  # beam 0 = port
    # a post 10 deg to starboard (+y) lights only the beams around +10 deg
    post = trimesh.creation.box(extents=(0.1, 0.1, 4.0))
    post.apply_translation((3.0 * math.cos(math.radians(10)), 3.0 * math.sin(math.radians(10)), 0.0))
    frame = son.render(World([WorldObject("post", post, CONCRETE)]), Pose())
    lit = np.flatnonzero(frame.intensity.sum(axis=0) > 0)
    assert lit.size > 0
    assert np.all(np.abs(np.degrees(frame.azimuths[lit]) - 10.0) < 1.5)
    assert np.all(lit > 48)


# ----------------------------------------------------------- 1. footprint


def test_floor_leading_and_trailing_edges_and_no_empty_bins(hf: SonarProfile) -> None:
    h, tilt = 1.2, math.radians(45.0)
    s = quiet(hf)
    frame = ImagingSonar(hf, s).render(floor_world(h), pitched_down(45.0))
    assert frame.intensity.shape == (512, 96)
    dr = (s.range_max - s.range_min) / s.n_samples
    phis = elevations(hf, s.elevation_rays)
    for b, theta in enumerate(beam_azimuths(hf)):
        col = frame.intensity[:, b]
        nz = np.flatnonzero(col > 0.0)
        assert nz.size > 0, f"beam {b} sees no floor"
        # the lowest ray (phi_min) meets the floor first, the highest one last
        r_first = h / down_component(theta, phis[0], tilt)
        r_last = h / down_component(theta, phis[-1], tilt)
        assert abs(nz[0] - math.floor((r_first - s.range_min) / dr)) <= 1, (b, nz[0], r_first)
        assert abs(nz[-1] - math.floor((r_last - s.range_min) / dr)) <= 1, (b, nz[-1], r_last)
        assert np.all(col[nz[0]:nz[-1] + 1] > 0.0), f"empty bin inside the floor footprint of beam {b}"
    assert frame.n_rays == 96 * 1000
    assert frame.n_hits == 96 * 1000
    assert frame.hit_counts == {"floor": {"total": 96000, "up": 96000}}


def grazing_gaps(profile: SonarProfile, spread: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Floor 0.5 m below a sonar tilted 10 deg down: far ranges meet it at grazing
    incidence, where adjacent elevation rays land ~17 mm apart (> the 9.8 mm bin)."""
    h, tilt = 0.5, math.radians(10.0)
    s = quiet(profile, spread=spread)
    frame = ImagingSonar(profile, s).render(floor_world(h), pitched_down(10.0))
    dr = (s.range_max - s.range_min) / s.n_samples
    phis = elevations(profile, s.elevation_rays)
    first = np.array([math.floor((h / down_component(th, phis[0], tilt) - s.range_min) / dr)
                      for th in beam_azimuths(profile)])
    # the highest rays meet the floor beyond range_max: the footprint runs to the last bin
    assert all(h / down_component(th, phis[-1], tilt) > s.range_max for th in beam_azimuths(profile))
    empty = np.array([np.count_nonzero(frame.intensity[f:, b] == 0.0) for b, f in enumerate(first)])
    lead = np.array([np.flatnonzero(frame.intensity[:, b] > 0)[0] for b in range(profile.n_beams)])
    return empty, lead - first, dr


def test_paper_method_leaves_empty_bins_and_spreading_fills_them(hf: SonarProfile) -> None:
    empty_paper, lead_paper, _ = grazing_gaps(hf, spread=False)
    empty_fixed, lead_fixed, _ = grazing_gaps(hf, spread=True)
    # the defect is real: every beam has empty bins inside the floor footprint
    assert np.all(empty_paper > 0)
    assert empty_paper.sum() > 1000
    # and spreading removes all of them, without moving the leading edge
    assert np.all(empty_fixed == 0)
    assert np.all(np.abs(lead_paper) <= 1) and np.all(np.abs(lead_fixed) <= 1)


def test_spread_deposit_splits_by_overlap() -> None:
    # interval [2.5, 5.25) bins: 0.5, 1, 1, 0.25 of 2.75; a point deposit; an interval cut by the window
    u = np.array([3.875, 7.3, 0.5])
    width = np.array([2.75, 0.0, 3.0])
    energy = np.array([1.0, 2.0, 3.0])
    beam = np.array([0, 1, 1])
    out = spread_deposit(u, width, energy, beam, n_samples=10, n_beams=2)
    want = np.zeros((10, 2))
    want[2:6, 0] = np.array([0.5, 1.0, 1.0, 0.25]) / 2.75
    want[7, 1] = 2.0
    want[0:2, 1] = 3.0 / 3.0  # [-1, 2): bins 0 and 1 get 1/3 each; 1/3 fell before the window
    np.testing.assert_allclose(out, want, rtol=1e-12, atol=1e-15)
    assert np.count_nonzero(out) == 7  # untouched cells are exactly zero


def test_spread_deposit_matches_brute_force_overlaps() -> None:
    rng = np.random.default_rng(11)
    n = 400
    u = rng.uniform(0.0, 50.0, n)
    width = np.where(rng.uniform(size=n) < 0.2, 0.0, rng.uniform(0.0, 6.0, n))
    energy = rng.uniform(0.1, 3.0, n)
    beam = rng.integers(0, 3, n)
    out = spread_deposit(u, width, energy, beam, n_samples=80, n_beams=3)
    want = np.zeros((80, 3))
    for ui, wi, ei, bi in zip(u, width, energy, beam):
        if wi == 0.0:
            want[int(ui), bi] += ei
            continue
        lo, hi = ui - wi / 2, ui + wi / 2
        for j in range(80):
            want[j, bi] += ei * max(0.0, min(hi, j + 1) - max(lo, j)) / wi
    np.testing.assert_allclose(out, want, rtol=1e-10, atol=1e-12)
    assert np.all(out[57:] == 0.0)  # past every interval: exactly zero, no running-sum residue


# ------------------------------------------------------- 2. intensity laws


def expected_wall_sums(profile: SonarProfile, distance: float, refl: float, n_el: int) -> np.ndarray:
    """Per beam, the sum of eq. 9 over its rays for a wall facing the sonar at ``distance``.

    Ray (theta, phi): c = cos phi cos theta = cos alpha, R = distance / c,
    I = k^2 refl I0 c^2 / R^4 / n_el = k^2 refl I0 c^6 / distance^4 / n_el.
    """
    th = beam_azimuths(profile)[:, None]
    ph = elevations(profile, n_el)[None, :]
    c = np.cos(ph) * np.cos(th)
    k2i0 = profile.k**2 * profile.source_intensity
    return (k2i0 * refl * c**6 / distance**4 / n_el).sum(axis=1)


def test_wall_follows_eq9_and_r4(hf: SonarProfile) -> None:
    son = ImagingSonar(hf, quiet(hf))
    refl = (CONCRETE.impedance - Z0) / (CONCRETE.impedance + Z0)
    sums = {}
    for d in (2.0, 4.0):
        frame = son.render(wall_world(d), Pose())
        sums[d] = frame.intensity.sum(axis=0)
        np.testing.assert_allclose(sums[d], expected_wall_sums(hf, d, refl, 1000), rtol=1e-3)
    np.testing.assert_allclose(sums[2.0] / sums[4.0], 2.0**4, rtol=0.01)


def single_ray(profile: SonarProfile, **changes: object) -> SonarSettings:
    """One ray per beam at elevation 0: every beam's echo lands in one cell (no spreading unless asked)."""
    return quiet(profile, **{"elevation_rays": 1, "spread": False, **changes})


def test_fixed_gain_image_follows_r4_and_tvg_undoes_it(hf: SonarProfile) -> None:
    s = single_ray(hf)
    son = ImagingSonar(hf, s)
    refl = (CONCRETE.impedance - Z0) / (CONCRETE.impedance + Z0)
    th = beam_azimuths(hf)
    dr = s.range_resolution
    pixels = {}
    for d in (1.5, 3.0):
        frame = son.render(wall_world(d), Pose())
        r = d / np.cos(th)
        rows = np.floor((r - s.range_min) / dr).astype(int)
        k2i0 = hf.k**2 * hf.source_intensity
        level = 10 * np.log10(refl * np.cos(th) ** 2 / r**4) + s.gain_db  # re k^2 I0
        want = np.clip(np.rint(255 * (level + s.dynamic_range_db) / s.dynamic_range_db), 0, 255)
        got = frame.image[rows, np.arange(96)].astype(float)
        assert np.all(np.abs(got - want) <= 1), (got - want)
        # the float intensity holds the same single-cell value exactly
        np.testing.assert_allclose(frame.intensity[rows, np.arange(96)], k2i0 * refl * np.cos(th) ** 2 / r**4,
                                   rtol=1e-5)
        pixels[d] = got
    # 40 log10(2) = 12.04 dB apart, on the 80 dB / 255 level scale
    np.testing.assert_allclose(pixels[1.5] - pixels[3.0], 40 * math.log10(2.0) * 255 / s.dynamic_range_db, atol=1.0)
    # with 40 log R TVG the same wall reads the same at both ranges
    tvg = s.replace(tvg=True, tvg_spreading_db=40.0, tvg_absorption=False)
    a = son.render(wall_world(1.5), Pose(), tvg).image.max(axis=0).astype(int)
    b = son.render(wall_world(3.0), Pose(), tvg).image.max(axis=0).astype(int)
    assert np.all(np.abs(a - b) <= 1)


@pytest.mark.parametrize("beta_deg", [25.0, 50.0])
def test_incidence_angle_gives_cos2(hf: SonarProfile, beta_deg: float) -> None:
    s = single_ray(hf, spread=True)
    son = ImagingSonar(hf, s)
    b = 60
    theta = beam_azimuths(hf)[b]
    d = 2.5
    point = (d * math.cos(theta), d * math.sin(theta))
    face_on = son.render(wall_world(d, yaw=theta, through=point), Pose()).intensity[:, b].sum()
    tilted = son.render(wall_world(d, yaw=theta + math.radians(beta_deg), through=point), Pose()).intensity[:, b].sum()
    np.testing.assert_allclose(tilted / face_on, math.cos(math.radians(beta_deg)) ** 2, rtol=0.01)


def test_materials_give_impedance_ratio(hf: SonarProfile) -> None:
    son = ImagingSonar(hf, quiet(hf))
    soft = Material("absorbing plastic", 3.5e6, acoustic_absorption=0.25)
    sums = {m.name: son.render(wall_world(2.0, m), Pose()).intensity.sum(axis=0) for m in (CONCRETE, PLASTIC, soft)}

    def gamma(z: float) -> float:
        return (z - Z0) / (z + Z0)

    np.testing.assert_allclose(sums["plastic"] / sums["concrete"], gamma(3.5e6) / gamma(8.0e6), rtol=0.01)
    np.testing.assert_allclose(sums["absorbing plastic"] / sums["plastic"], 0.75, rtol=0.01)


def test_water_absorption_and_its_tvg(hf: SonarProfile) -> None:
    s = single_ray(hf)
    son = ImagingSonar(hf, s)
    alpha = hf.absorption_db_per_m
    # Francois & Garrison (1982) pure-water term at 20 degC: A3 f^2 dB/km with f in kHz
    a3 = 4.937e-4 - 2.59e-5 * 20 + 9.11e-7 * 20**2 - 1.50e-8 * 20**3
    assert alpha == pytest.approx(a3 * 1800**2 / 1000, rel=1e-9)
    assert 0.6 < alpha < 0.8
    d = 4.0
    r = d / np.cos(beam_azimuths(hf))
    off = son.render(wall_world(d), Pose()).intensity.sum(axis=0)
    on = son.render(wall_world(d), Pose(), s.replace(absorption=True)).intensity.sum(axis=0)
    np.testing.assert_allclose(on / off, 10 ** (-2 * alpha * r / 10), rtol=1e-6)
    img_off = son.render(wall_world(d), Pose()).image
    img_on = son.render(wall_world(d), Pose(), s.replace(absorption=True, tvg=True, tvg_spreading_db=0.0,
                                                          tvg_absorption=True)).image
    assert np.abs(img_on.astype(int) - img_off.astype(int)).max() <= 1


# ------------------------------------------------------------ realism


def test_beam_pattern_matrix_shape_of_sinc2() -> None:
    bw = math.radians(0.3)
    az = (0.0, bw / 2, 1.4303 * bw / (2 * 0.44295), 1.0 * bw / (2 * 0.44295))
    k = beam_pattern_matrix(az, bw)
    assert k[0, 0] == pytest.approx(1.0)
    assert k[0, 1] == pytest.approx(0.5, abs=1e-3)  # -3 dB at half the beam width
    assert 10 * math.log10(k[0, 2]) == pytest.approx(-13.26, abs=0.05)  # first side lobe
    assert k[0, 3] == pytest.approx(0.0, abs=1e-12)  # first null
    np.testing.assert_allclose(k, k.T)


def test_speckle_and_noise_statistics(hf: SonarProfile) -> None:
    base = quiet(hf)
    son = ImagingSonar(hf, base, seed=7)
    world = floor_world(1.2)
    clean = son.render(world, pitched_down(45.0)).intensity
    speck = son.render(world, pitched_down(45.0), base.replace(speckle=True)).intensity
    lit = clean > 0
    ratio = speck[lit] / clean[lit]
    # Rayleigh amplitude -> exponential intensity factor: mean 1, median ln 2
    assert ratio.size > 3000
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.06)
    assert np.median(ratio) == pytest.approx(math.log(2.0), abs=0.05)
    assert np.all(speck[~lit] == 0.0)
    empty = World([WorldObject("far", trimesh.creation.box(extents=(1, 1, 1)), CONCRETE)])
    noisy = son.render(empty, Pose.from_xyz_rpy((0, 0, -50), (0, 0, 0)), base.replace(noise=True, noise_level_db=-90.0))
    assert noisy.n_hits == 0
    assert noisy.intensity.mean() == pytest.approx(1e-9, rel=0.03)


# ------------------------------------------------- 4. determinism and gain


def test_determinism_and_seeds(hf: SonarProfile) -> None:
    world = floor_world(1.2)
    pose = pitched_down(45.0)
    off = quiet(hf)
    a = ImagingSonar(hf, off).render(world, pose)
    b = ImagingSonar(hf, off, seed=99).render(world, pose)
    assert np.array_equal(a.intensity, b.intensity) and np.array_equal(a.image, b.image)
    real = hf.default_settings()
    assert real.speckle and real.noise and real.beam_pattern
    s1 = ImagingSonar(hf, real, seed=1)
    f1 = s1.render(world, pose)
    f1_next = s1.render(world, pose)
    f1_again = ImagingSonar(hf, real, seed=1).render(world, pose)
    f2 = ImagingSonar(hf, real, seed=2).render(world, pose)
    assert np.array_equal(f1.intensity, f1_again.intensity) and np.array_equal(f1.image, f1_again.image)
    assert not np.array_equal(f1.intensity, f2.intensity)
    assert not np.array_equal(f1.intensity, f1_next.intensity)  # a new frame draws new noise
    assert f1_next.frame_index == 1
    replay = ImagingSonar(hf, real, seed=1).render(world, pose, frame_index=1)
    assert np.array_equal(replay.intensity, f1_next.intensity)


def test_paper_gain_is_relative_and_linear(hf: SonarProfile) -> None:
    frame = ImagingSonar(hf, quiet(hf).replace(gain_mode="paper")).render(floor_world(1.2), pitched_down(45.0))
    assert frame.image.max() == 255
    top = frame.intensity.max()
    np.testing.assert_array_equal(frame.image, np.rint(255 * frame.intensity / top).astype(np.uint8))
    paper = hf.default_settings().paper_model()
    assert (paper.gain_mode, paper.spread, paper.speckle, paper.noise, paper.beam_pattern) == ("paper", False, False, False, False)


def test_sample_uses_vehicle_pose_and_mount(hf: SonarProfile) -> None:
    world = floor_world(3.0)
    state = VehicleState(time=12.5, position=np.array([1.0, 2.0, 1.8]), attitude=np.array([0.0, 0.0, 0.7]))
    mount = Pose.from_xyz_rpy((0.3, 0.0, 0.2), (0.0, math.radians(-45.0), 0.0))
    son = ImagingSonar(hf, quiet(hf))
    frame = son.sample(world, state, mount)
    # the sensor ends up 3.0 - 1.8 - 0.2 = 1.0 m above the floor top
    direct = son.render(floor_world(1.0), pitched_down(45.0))
    assert frame.time == 12.5
    assert frame.pose.position == pytest.approx([1.0 + 0.3 * math.cos(0.7), 2.0 + 0.3 * math.sin(0.7), 2.0])
    # float32 ray casting from a different origin moves hits by ~1e-7 m: cells at a
    # bin edge change by up to ~1e-3 of a ray's echo, per-beam sums do not
    np.testing.assert_allclose(frame.intensity, direct.intensity, rtol=1e-3, atol=1e-3 * direct.intensity.max())
    np.testing.assert_allclose(frame.intensity.sum(axis=0), direct.intensity.sum(axis=0), rtol=1e-5)


# -------------------------------------------------------- 5. profiles


def test_didson_profiles_load_documented_values() -> None:
    hf = load_sonar_profile(HF)
    assert hf.n_beams == 96 and hf.n_samples == 512
    assert hf.azimuth_limits == pytest.approx((math.radians(-14.5), math.radians(14.5)))
    assert hf.elevation_limits == pytest.approx((math.radians(-7.0), math.radians(7.0)))
    assert math.degrees(hf.beam_spacing) == pytest.approx(0.3, rel=0.01)
    assert (hf.range_min, hf.range_max) == pytest.approx((0.83, 5.83))
    assert hf.frequency == pytest.approx(1.8e6)
    assert math.degrees(hf.beam_width_azimuth) == pytest.approx(0.3)
    assert math.degrees(hf.beam_width_elevation) == pytest.approx(14.0)
    assert hf.default_settings().elevation_rays == 1000
    assert 10.0 <= hf.frame_rate <= 21.0
    assert "paper" in hf.sources["window.range_min"]
    lf = load_sonar_profile(LF)
    assert lf.n_beams == 48 and lf.n_samples == 512
    assert math.degrees(lf.beam_spacing) == pytest.approx(0.6, rel=0.01)
    assert lf.frequency == pytest.approx(1.1e6)
    # extended LF window, start code 2 and length code 2: 2 x 2 x 0.419 m and 20 m long
    assert lf.range_min == pytest.approx(4 * 0.419)
    assert lf.range_max - lf.range_min == pytest.approx(20.0)
    assert lf.absorption_db_per_m == pytest.approx(pure_water_absorption(1.1e6, 293.15))


def broken(tmp_path: Path, old: str, new: str) -> Path:
    text = HF.read_text()
    assert old in text
    p = tmp_path / "broken.toml"
    p.write_text(text.replace(old, new, 1))
    return p


@pytest.mark.parametrize(
    ("old", "new", "key", "words"),
    [
        ("count            =", "coutn            =", "beams.coutn", "did you mean 'count'"),
        ('frequency         = { value = 1.8, unit = "MHz"', 'frequency         = { value = 1.8, unit = "m"',
         "acoustics.frequency", "not a unit of 'Hz'"),
        ("range_max = { value = 5.83,", "range_max = { value = 0.5,", "window.range_min", "must be <"),
        ("samples   = { value = 512,", "samples   = { value = 51.2,", "window.samples", "whole number"),
        ("speckle      = true", "speckle      = 1", "realism.speckle", "true or false"),
        ('mode           = "fixed"', 'mode           = "auto"', "gain.mode", "must be one of"),
        ("min_elevation_rays = { value = 100,", "min_elevation_rays = { value = 2000,", "beams.min_elevation_rays",
         "1..elevation_rays (1000)"),
        ("adaptive_rays      = true", "adaptive_rays      = 0", "beams.adaptive_rays", "true or false"),
    ],
)
def test_broken_profile_names_the_key(tmp_path: Path, old: str, new: str, key: str, words: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_sonar_profile(broken(tmp_path, old, new))
    assert err.value.key == key
    assert key in str(err.value) and words in str(err.value)
    assert err.value.line is not None


def test_settings_validation() -> None:
    ok = SonarSettings(range_min=1.0, range_max=5.0, n_samples=100)
    assert ok.range_resolution == pytest.approx(0.04)
    np.testing.assert_allclose(ok.ranges[[0, -1]], [1.02, 4.98])
    for bad in ({"range_min": 5.0}, {"n_samples": 0}, {"gain_mode": "auto"}, {"spread_max_bins": 0.0},
                {"elevation_rays": 2.5}, {"dynamic_range_db": -1.0}, {"speckle": 1}):
        with pytest.raises(ValueError):
            ok.replace(**bad)


# ------------------------------------------------------------ the faster frame equals the one before
#
# The render before issue #15 (world.cast per ray, float64 columns, row-major cells, two
# exponential() calls), kept here verbatim as the reference the faster path is held to.


def _spread_before(u, width, energy, beam, n_samples, n_beams):
    ns, nb = n_samples, n_beams
    pad = int(np.ceil(0.5 * float(width.max(initial=0.0)))) + 1
    rows = ns + 2 * pad
    half = 0.5 * width
    a = u - half + pad
    b = u + half + pad
    i0 = a.astype(np.int64)
    i1 = b.astype(np.int64)
    single = i1 == i0
    with np.errstate(divide="ignore", invalid="ignore"):
        density = energy / width
        lead = (i0 + 1 - a) * density
    first = np.where(single, energy, lead)
    total = np.bincount(i0 * nb + beam, weights=first, minlength=rows * nb).astype(float)
    multi = np.flatnonzero(~single)
    if multi.size:
        m0, m1, mb, md = i0[multi], i1[multi], beam[multi], density[multi]
        total += np.bincount(m1 * nb + mb, weights=md * (b[multi] - m1), minlength=rows * nb)
        inner = m1 > m0 + 1
        if inner.any():
            bi, dens = mb[inner], md[inner]
            start, stop, size = (m0[inner] + 1) * nb + bi, m1[inner] * nb + bi, rows * nb
            run = np.bincount(start, weights=dens, minlength=size) - np.bincount(stop, weights=dens, minlength=size)
            cnt = np.bincount(start, minlength=size) - np.bincount(stop, minlength=size)
            run = np.cumsum(run.reshape(rows, nb), axis=0)
            is_open = np.cumsum(cnt.reshape(rows, nb), axis=0) > 0
            total += np.where(is_open, run, 0.0).ravel()
    return total.reshape(rows, nb)[pad:pad + ns]


def _render_before(sonar: ImagingSonar, world: World, pose: Pose, s: SonarSettings, frame_index: int):
    """(intensity, image, hit_counts, n_hits) as the render before issue #15 made them."""
    from hilsim.sim.sonar import _ray_fan, paper_gain_levels, tvg_db

    p = sonar.profile
    nb, ns = p.n_beams, s.n_samples
    dirs_s, ddphi_s, beam_all, dphi = _ray_fan(p.azimuth_limits[0], p.azimuth_limits[1], nb,
                                               p.elevation_limits[0], p.elevation_limits[1], s.elevation_rays)
    rot = np.asarray(pose.rotation, dtype=float)
    dirs = dirs_s @ rot.T
    origins = np.broadcast_to(np.asarray(pose.position, dtype=float), dirs.shape)
    hits = world.cast(origins, dirs, t_min=s.range_min, t_max=s.range_max)
    hit = hits.tri >= 0
    nrm = hits.normal @ rot
    n_dot_d = (nrm * dirs_s).sum(axis=1)
    r = hits.t
    refl = np.abs(world.obj_reflection)[hits.obj]
    energy = (p.k * p.k * p.source_intensity / s.elevation_rays) * refl * n_dot_d ** 2 / r ** 4
    if s.absorption:
        energy *= 10.0 ** (-0.2 * p.absorption_db_per_m * np.where(hit, r, 0.0))
    dr = s.range_resolution
    u = np.clip((r - s.range_min) / dr, 0.0, ns * (1.0 - 1e-12))
    if s.spread:
        with np.errstate(divide="ignore", invalid="ignore"):
            width = np.abs(r * (nrm * ddphi_s).sum(axis=1) / n_dot_d) * dphi / dr
        width = np.fmin(width, s.spread_max_bins)
        width[~hit] = 0.0
        intensity = _spread_before(u, width, energy, beam_all, ns, nb)
    else:
        cell = u.astype(np.int64) * nb + beam_all
        intensity = np.bincount(cell, weights=energy, minlength=ns * nb).astype(float).reshape(ns, nb)
    if s.beam_pattern:
        intensity = intensity @ beam_pattern_matrix(tuple(p.azimuths.tolist()), p.beam_width_azimuth)
    if s.speckle or s.noise:
        g = np.random.default_rng([sonar.seed, frame_index])
        if s.speckle:
            intensity = intensity * g.exponential(1.0, intensity.shape)
        if s.noise:
            mean = p.k * p.k * p.source_intensity * 10.0 ** (s.noise_level_db / 10.0)
            intensity = intensity + g.exponential(mean, intensity.shape)
    if s.gain_mode == "paper":
        image = paper_gain_levels(intensity)
    else:
        ref = p.k * p.k * p.source_intensity
        with np.errstate(divide="ignore"):
            level = 10.0 * np.log10(intensity / ref)
        level += (tvg_db(s.ranges, s, p.absorption_db_per_m) + s.gain_db)[:, None]
        px = np.rint((level + s.dynamic_range_db) * (255.0 / s.dynamic_range_db))
        image = np.clip(np.nan_to_num(px, nan=0.0, neginf=0.0), 0.0, 255.0).astype(np.uint8)
    return intensity, image, world.hit_counts(hits), int(np.count_nonzero(hit))


def tank_world() -> World:
    """The water tank of benchmarks/bench_sonar.py: floor 1.2 m below, a cuboid 0.9 m ahead."""
    floor = trimesh.creation.box(extents=(10.0, 10.0, 0.1))
    floor.apply_translation((0.0, 0.0, 1.25))
    cuboid = trimesh.creation.box(extents=(0.35, 0.5, 0.3))
    cuboid.apply_translation((1.075, 0.0, 1.05))
    return World([WorldObject("floor", floor, CONCRETE), WorldObject("cuboid", cuboid, PLASTIC)], Water())


def _case(hf: SonarProfile, case: str, s: SonarSettings) -> tuple[SonarSettings, Pose]:
    if case.startswith("grazing"):  # 0.5 m above the floor, 10 deg down: echoes spread over several bins
        return s.replace(n_samples=2048), Pose.from_xyz_rpy((0.0, 0.0, 0.7), (0.0, -math.radians(10.0), 0.0))
    return s, pitched_down(45.0)


@pytest.mark.parametrize("case", ["tank 45 deg", "grazing 10 deg, 2048 bins"])
@pytest.mark.parametrize("mode", ["realism off", "paper model", "beam pattern + absorption"])
def test_the_faster_frame_equals_the_frame_before(hf: SonarProfile, case: str, mode: str) -> None:
    """Without the random parts the render is the one before issue #15 up to float32
    rounding of the per-ray echo (Embree's ranges are float32 already) and of the beam
    pattern: intensities within 2e-5 relative of the cell's value (plus 1e-6 of the
    brightest, for cancellation in the running sums), the same hit counts, and images
    equal but for a rare pixel a level off (a level at a rounding edge)."""
    world = tank_world()
    full = hf.default_settings().replace(elevation_rays=1000, n_samples=512)
    s = {"realism off": full.realism_off(), "paper model": full.paper_model(),
         "beam pattern + absorption": full.replace(speckle=False, noise=False)}[mode]
    s, pose = _case(hf, case, s)
    sonar = ImagingSonar(hf, s, seed=3)
    frame = sonar.render(world, pose, s, frame_index=0)
    intensity, image, counts, n_hits = _render_before(sonar, world, pose, s, 0)
    assert frame.hit_counts == counts and frame.n_hits == n_hits and n_hits > 0
    assert frame.intensity.shape == intensity.shape == (s.n_samples, hf.n_beams)
    np.testing.assert_allclose(frame.intensity, intensity, rtol=2e-5, atol=1e-6 * intensity.max())
    assert np.array_equal(frame.intensity == 0.0, intensity == 0.0) or s.beam_pattern
    diff = np.abs(frame.image.astype(int) - image.astype(int))
    assert diff.max() <= 1 and np.count_nonzero(diff) <= 1e-3 * diff.size, (diff.max(), np.count_nonzero(diff))


@pytest.mark.parametrize("case", ["tank 45 deg", "grazing 10 deg, 2048 bins"])
def test_the_faster_speckle_and_noise_have_the_statistics_before(hf: SonarProfile, case: str) -> None:
    """Speckle and noise now come from float32 uniforms through the inverse CDF (other
    numbers than before, same law): per cell, the speckle factor (frame with speckle / the
    same frame without) and the noise (frame with noise - without) follow Exp(1) and
    Exp(mean) (mean, variance, median ln 2, 90 % quantile ln 10 against the law, pooled
    over frames); the full-realism images match the ones before in their level statistics
    per range band (mean within 1.5 levels, spread within 10 %)."""
    world = tank_world()
    full, pose = _case(hf, case, hf.default_settings().replace(elevation_rays=1000, n_samples=512))
    clean = full.replace(speckle=False, noise=False)
    sonar = ImagingSonar(hf, full, seed=11)
    base = sonar.render(world, pose, clean, frame_index=0).intensity
    on = base > 1e-6 * base.max()
    speckle, noise = [], []
    mean = hf.k ** 2 * hf.source_intensity * 10.0 ** (full.noise_level_db / 10.0)
    new_img, old_img = [], []
    for i in range(3):
        speckle.append(sonar.render(world, pose, full.replace(noise=False), frame_index=i).intensity[on] / base[on])
        noise.append((sonar.render(world, pose, full.replace(speckle=False), frame_index=i).intensity - base).ravel()
                     / mean)
        new_img.append(sonar.render(world, pose, full, frame_index=i).image.astype(float))
        old_img.append(_render_before(sonar, world, pose, full, i)[1].astype(float))
    for x in (np.concatenate(speckle), np.concatenate(noise)):
        assert x.size > 20000
        assert x.mean() == pytest.approx(1.0, abs=0.03) and x.var() == pytest.approx(1.0, abs=0.08)
        assert np.median(x) == pytest.approx(math.log(2.0), abs=0.03)
        assert np.quantile(x, 0.9) == pytest.approx(math.log(10.0), abs=0.08)
        assert x.min() >= -1e-6 and x.max() < 17.0
    new, old = np.stack(new_img), np.stack(old_img)
    for band in np.array_split(np.arange(full.n_samples), 8):
        a, b = new[:, band], old[:, band]
        assert a.mean() == pytest.approx(b.mean(), abs=1.5), band[0]
        assert a.std() == pytest.approx(b.std(), rel=0.1, abs=0.5), band[0]


@pytest.mark.parametrize("tilt_deg, n_samples", [(30.0, 512), (20.0, 1024)])
def test_a_tenth_of_the_rays_with_spreading_leaves_no_empty_bin(hf: SonarProfile, tilt_deg: float,
                                                                  n_samples: int) -> None:
    """Deadline-aware rendering casts as few as the profile's min_elevation_rays (100 of
    1000): with the spreading (its width cap widened as the rays are fewer, as the render
    worker does) every range bin the floor lights at 1000 rays is lit at 100, at the same
    level (energy per ray is 1/rays); without spreading the same frame has empty bins."""
    assert hf.min_elevation_rays == 100 and hf.adaptive_rays
    world = floor_world(1.2)
    s = quiet(hf, n_samples=n_samples)
    sonar = ImagingSonar(hf, s)
    pose = pitched_down(tilt_deg)
    full = sonar.render(world, pose, s)
    rows = np.flatnonzero((full.intensity > 0).all(axis=1))  # range rows the floor fills at full count
    assert rows.size > 50
    few = s.replace(elevation_rays=100, spread_max_bins=s.spread_max_bins * 10)
    low = sonar.render(world, pose, few)
    assert low.n_rays == hf.n_beams * 100
    assert np.count_nonzero(low.intensity[rows] == 0) == 0
    assert np.median(low.intensity[rows] / full.intensity[rows]) == pytest.approx(1.0, rel=0.01)
    literal = sonar.render(world, pose, few.replace(spread=False))
    assert np.count_nonzero(literal.intensity[rows] == 0) > 100
