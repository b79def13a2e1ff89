"""Wet ground effect: physics, scope (ground only), identity, determinism, edge cases.

The contract runs on a synthetic full sweep; that heavy wetness leaves most of the
real KITTI road is checked on the real scan."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ground_scenes import make_scene
from omnilidar.domains.effects import wet_ground as W
from omnilidar.domains.effects.base import SEVERITY_NAMES
from omnilidar.domains.ground import estimate_ground
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Boxes, Scan
from omnilidar.lidar.sensors import PRESETS

from real_samples import real_file
KITTI = PRESETS["kitti_hdl64e"]
RNG = lambda seed=0: np.random.default_rng(seed)  # noqa: E731


def _with_ground(pts: np.ndarray) -> tuple[Scan, np.ndarray]:
    """A sweep's points with random labels, instances and rings, and its estimated ground."""
    n = len(pts)
    rng = RNG(5)
    scan = Scan(
        pts,
        semantic=rng.integers(0, 260, n),
        instance=rng.integers(0, 50, n),
        ring=rng.integers(0, 64, n),
        boxes=Boxes(np.ones((2, 7), np.float32), np.array(["Car", "Pedestrian"])),
    )
    return scan, estimate_ground(scan, KITTI)


def _all_runs(scan: Scan, ground: np.ndarray) -> dict:
    return {
        sev: W.apply(scan, W.draw_params(sev, RNG()), KITTI, RNG(), ground=ground, return_info=True)
        for sev in SEVERITY_NAMES
    }


@pytest.fixture(scope="module")
def sweep(synthetic_sweep):
    """A full synthetic HDL-64E sweep and its estimated ground."""
    return _with_ground(synthetic_sweep.points)


@pytest.fixture(scope="module")
def runs(sweep):
    return _all_runs(*sweep)


def flat_ground(n_side=40, intensity=0.2, height=1.73, extent=30.0):
    """A flat grid of ground points whose normalised intensity I / cos(theta) is
    constant (so the linear power fit is exact: a = 0, b = intensity)."""
    g = np.linspace(-extent, extent, n_side)
    x, y = np.meshgrid(g, g)
    x, y = x.ravel(), y.ravel()
    keep = np.hypot(x, y) > 3
    x, y = x[keep], y[keep]
    z = np.full_like(x, -height)
    cos_t = height / np.sqrt(x**2 + y**2 + z**2)
    return Scan(np.column_stack([x, y, z, intensity * cos_t]).astype(np.float32))


# ---------------------------------------------------------------- interface


def test_interface():
    assert W.NEEDS_GROUND is True
    assert set(W.SEVERITIES) == set(SEVERITY_NAMES)
    assert [W.SEVERITIES[s]["water_height_mm"] for s in SEVERITY_NAMES] == [0.2, 1.0, 1.2]
    assert [W.SEVERITIES[s]["noise_floor"] for s in SEVERITY_NAMES] == [0.3, 0.3, 0.7]
    for knob, values in W.FIDELITY_LEVELS.items():
        assert W.DEFAULT_FIDELITY[knob] in values
    p = W.draw_params("moderate", RNG())
    assert p == {"water_height_mm": 1.0, "noise_floor": 0.3, "pavement_depth_mm": 1.2}
    with pytest.raises(InputError, match="unknown severity"):
        W.draw_params("drizzle", RNG())


def test_bad_input_raises_input_error(sweep):
    scan, ground = sweep
    with pytest.raises(InputError):
        W.apply(scan, {"water_height_mm": -1.0}, KITTI, RNG(), ground=ground)
    with pytest.raises(InputError):
        W.apply(scan, {"water_height_mm": float("nan")}, KITTI, RNG(), ground=ground)
    with pytest.raises(InputError):
        W.apply(scan, {"noise_floor": 0.3}, KITTI, RNG(), ground=ground)
    with pytest.raises(InputError, match="ground mask"):
        W.apply(scan, W.draw_params("heavy", RNG()), KITTI, RNG(), ground=ground[:-1])
    with pytest.raises(InputError, match="fidelity"):
        W.apply(scan, W.draw_params("heavy", RNG()), KITTI, RNG(), ground=ground, fidelity={"bins": 3})


# ---------------------------------------------------------------- physics


def test_fresnel_analytic():
    n1, n2 = W.N_AIR, W.N_WATER
    rs, rp = W.fresnel_reflectance(np.array([1.0]))
    r0 = ((n2 - n1) / (n1 + n2)) ** 2
    assert rs[0] == pytest.approx(r0) and rp[0] == pytest.approx(r0)  # normal incidence
    brewster = np.arctan(n2 / n1)
    assert W.fresnel_reflectance(np.array([np.cos(brewster)]))[1][0] == pytest.approx(0.0, abs=1e-12)
    rs, rp = W.fresnel_reflectance(np.array([0.0]))
    assert rs[0] == pytest.approx(1.0) and rp[0] == pytest.approx(1.0)  # grazing: mirror
    # Snell at 60 deg, s-polarisation by hand.
    ci = 0.5
    ct = np.sqrt(1 - (n1 / n2 * np.sin(np.arccos(ci))) ** 2)
    assert W.fresnel_reflectance(np.array([ci]))[0][0] == pytest.approx(((n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)) ** 2)
    # Total with multiple reflections at normal incidence, by hand.
    rho = 0.3
    assert W.wet_transmittance(np.array([1.0]), np.array([rho]))[0] == pytest.approx((1 - r0) ** 2 * rho / (1 - rho * r0))
    # Never more than the dry Lambertian return, at any angle and albedo.
    c = np.linspace(0, 1, 101)[:, None]
    r = np.linspace(0.05, 1, 20)[None, :]
    assert np.all(W.wet_transmittance(c, r) <= r + 1e-15)


def test_hand_computed_flat_ground():
    """Constant I / cos(theta) = 0.2 -> P_out = 15 * 0.2, rho = 1/15; the wet
    intensity of every point is I [(1 - f) + f T_tot(theta, 1/15) / (1/15)]."""
    scan = flat_ground(intensity=0.2)
    ground = np.ones(len(scan), bool)
    f = 1.0 / 1.2
    out, info = W.apply(scan, {"water_height_mm": 1.0, "noise_floor": 0.0}, KITTI, RNG(), ground=ground, return_info=True)
    assert not info["lost"].any()  # noise floor 0: nothing can drop
    d = np.linalg.norm(scan.xyz.astype(np.float64), axis=1)
    cos_t = 1.73 / d
    rho = np.full(len(d), 1 / 15)
    expect = scan.intensity * ((1 - f) + f * W.wet_transmittance(cos_t, rho) / rho)
    np.testing.assert_allclose(out.intensity, expect, rtol=1e-5)
    # A uniform ground has its 5 % envelope at 0.2: floor 0.7 * 0.2 drops exactly
    # the points whose wet normalised intensity falls under 0.14.
    out, info = W.apply(scan, {"water_height_mm": 1.2, "noise_floor": 0.7}, KITTI, RNG(), ground=ground, return_info=True)
    wet_norm = 0.2 * W.wet_transmittance(cos_t, rho) / rho
    np.testing.assert_array_equal(info["lost"], wet_norm <= 0.7 * 0.2 * (1 + 1e-7))
    assert 0 < info["lost"].sum() < len(scan)  # grazing points go, steep ones stay


def test_pitched_sensor_uses_the_ground_normal():
    """On a drone pitched 20 deg the incidence comes from the fitted ground
    normal, not the sensor's z axis: with I / cos(theta_true) constant the
    result matches the hand formula evaluated with the true incidence."""
    drone = PRESETS["drone_os64"]
    scan = make_scene(drone, RNG(3), n_cars=0, n_poles=0, n_people=0)
    ground = scan.semantic == 40
    xyz = scan.xyz.astype(np.float64)
    u = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    up = np.array([-np.sin(np.deg2rad(20.0)), 0.0, np.cos(np.deg2rad(20.0))])
    cos_true = -(u @ up)
    pts = scan.points.copy()
    pts[ground, 3] = 0.2 * cos_true[ground]
    scan = scan.with_points(pts)
    out, info = W.apply(scan, {"water_height_mm": 1.2, "noise_floor": 0.0}, drone, RNG(), ground=ground,
                        return_info=True)
    assert not info["lost"].any()
    rho = np.full(ground.sum(), 1 / 15)
    expect = scan.intensity[ground] * W.wet_transmittance(cos_true[ground], rho) / rho
    np.testing.assert_allclose(out.intensity[ground], expect, rtol=2e-3)


def _check_monotone(scan: Scan, ground: np.ndarray, runs: dict) -> list[int]:
    """Checks losses grow and intensity drops with severity; returns the losses per severity."""
    lost = [runs[s][1]["lost"].sum() for s in SEVERITY_NAMES]
    assert lost[0] <= lost[1] < lost[2]
    # Mean intensity of surviving ground points drops with water height.
    means = []
    for s in SEVERITY_NAMES:
        out, info = runs[s]
        kept_ground = ground[~info["lost"]]
        means.append(out.intensity[kept_ground].mean())
    assert scan.intensity[ground].mean() > means[0] > means[1]
    # At equal noise floor (light vs moderate), more water -> every point darker or equal.
    lm = W.apply(scan, {"water_height_mm": 0.2, "noise_floor": 0.0}, KITTI, RNG(), ground=ground)
    mm = W.apply(scan, {"water_height_mm": 1.0, "noise_floor": 0.0}, KITTI, RNG(), ground=ground)
    assert np.all(mm.intensity <= lm.intensity)
    return lost


def test_monotone_in_severity(sweep, runs):
    _check_monotone(*sweep, runs)


def test_heavy_wet_ground_does_not_erase_the_real_kitti_road():
    scan, ground = _with_ground(np.fromfile(real_file("kitti_object/velodyne/000000.bin"), np.float32).reshape(-1, 4))
    lost = _check_monotone(scan, ground, _all_runs(scan, ground))
    assert lost[2] < 0.3 * ground.sum()  # heavy wets, it does not erase the road


def test_only_ground_changes_order_kept(sweep, runs):
    scan, ground = sweep
    for sev in SEVERITY_NAMES:
        out, info = runs[sev]
        kept = ~info["lost"]
        assert not info["lost"][~ground].any() and not info["changed"][~ground].any()
        assert len(out) == kept.sum() and not info["weather"].any() and info["weather"].shape == (len(out),)
        # xyz of every kept point unchanged and in input order; non-ground bit for bit.
        assert np.array_equal(out.xyz, scan.xyz[kept])
        assert np.array_equal(out.points[~ground[kept]], scan.points[~ground & kept])
        # Never brighter; changed = kept ground points whose intensity moved.
        assert np.all(out.intensity <= scan.intensity[kept])
        assert np.array_equal(info["changed"][kept], out.intensity != scan.intensity[kept])
        assert not (info["changed"] & info["lost"]).any()
        # Labels, instances, rings follow their points; boxes carried.
        assert np.array_equal(out.semantic, scan.semantic[kept])
        assert np.array_equal(out.instance, scan.instance[kept])
        assert np.array_equal(out.ring, scan.ring[kept])
        assert out.boxes is scan.boxes


def test_zero_remission_points_are_never_lost(sweep, runs):
    scan, ground = sweep
    zero = ground & (scan.intensity == 0)
    assert zero.sum() > 100
    for sev in SEVERITY_NAMES:
        assert not runs[sev][1]["lost"][zero].any()


def test_scale_free(sweep, runs):
    """The same decision whatever the intensity unit or receiver gain."""
    scan, ground = sweep
    params = W.draw_params("heavy", RNG())
    ref = runs["heavy"][1]["lost"]
    nusc_like = replace(scan, points=scan.points * np.array([1, 1, 1, 255], np.float32), intensity_scale=255.0)
    sensor255 = replace(KITTI, intensity_scale=255.0)
    out, info = W.apply(nusc_like, params, sensor255, RNG(), ground=ground, return_info=True)
    assert np.array_equal(info["lost"], ref)
    np.testing.assert_allclose(out.intensity / 255.0, runs["heavy"][0].intensity, atol=1e-6)
    assert out.intensity.max() <= 255.0
    dimmer = replace(scan, points=scan.points * np.array([1, 1, 1, 0.5], np.float32))
    _, info = W.apply(dimmer, params, KITTI, RNG(), ground=ground, return_info=True)
    assert np.array_equal(info["lost"], ref)


def test_zero_severity_is_identity(sweep):
    scan, ground = sweep
    for params in ({"water_height_mm": 0.0, "noise_floor": 0.7}, {"water_height_mm": 0.0}):
        out, info = W.apply(scan, params, KITTI, RNG(), ground=ground, return_info=True)
        assert out is scan
        assert not info["lost"].any() and not info["changed"].any() and not info["weather"].any()
    out = W.apply(scan, W.draw_params("heavy", RNG()), KITTI, RNG(), ground=np.zeros(len(scan), bool))
    assert out is scan and np.array_equal(out.points, scan.points)


def test_deterministic_and_pure(sweep):
    scan, ground = sweep
    before = scan.points.copy()
    params = W.draw_params("heavy", RNG())
    for fid in (None, {"fit_points": 1024}):
        a = W.apply(scan, params, KITTI, RNG(7), ground=ground, fidelity=fid)
        b = W.apply(scan, params, KITTI, RNG(7), ground=ground, fidelity=fid)
        assert np.array_equal(a.points, b.points) and np.array_equal(a.semantic, b.semantic)
    assert np.array_equal(scan.points, before)  # input untouched


def test_ground_estimated_when_not_given():
    scan = make_scene(KITTI, RNG(1))
    params = W.draw_params("heavy", RNG())
    a = W.apply(scan, params, KITTI, RNG())
    b = W.apply(scan, params, KITTI, RNG(), ground=estimate_ground(scan, KITTI))
    assert np.array_equal(a.points, b.points)


@pytest.mark.parametrize(
    "pts",
    [
        np.zeros((0, 4)),
        [[5.0, 0.0, -1.73, 0.3]],
        [[0.0, 0.0, 0.0, 0.5]],
        [[0.0, 0.0, 0.0, 0.0], [1e-7, 0.0, 0.0, 0.2], [4.0, 0.0, -1.73, 0.0]],
        [[4.0, 0.0, -1.73, 0.0], [8.0, 1.0, -1.73, 0.0], [12.0, 2.0, -1.73, 0.0]],
        [[4.0, 0.0, -1.73, 1.0], [4.0, 0.0, -1.73, 1.0]],
        [[3.0, 0.0, 1.0, 0.4], [-3.0, 0.0, 1.0, 0.4], [0.0, 3.0, 1.0, 0.4]],  # "ground" above the sensor
    ],
)
def test_degenerate_scans(pts):
    scan = Scan(np.asarray(pts, np.float32).reshape(-1, 4))
    ground = np.ones(len(scan), bool)
    for sev in SEVERITY_NAMES:
        out, info = W.apply(scan, W.draw_params(sev, RNG()), KITTI, RNG(), ground=ground, return_info=True)
        assert np.all(np.isfinite(out.points))
        assert np.all((out.intensity >= 0) & (out.intensity <= 1))
        assert len(out) == len(scan) - info["lost"].sum()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(0, 300),
    seed=st.integers(0, 2**31 - 1),
    h=st.floats(0.0, 5.0),
    nf=st.floats(0.0, 3.0),
    scale=st.sampled_from([1.0, 255.0]),
    fit_points=st.sampled_from(W.FIDELITY_LEVELS["fit_points"]),
    range_bins=st.sampled_from(W.FIDELITY_LEVELS["range_bins"]),
)
def test_property_no_nan_ranges_intensities(n, seed, h, nf, scale, fit_points, range_bins):
    rng = RNG(seed)
    xyz = rng.normal(0, 1, (n, 3)) * rng.choice([1e-6, 0.5, 5.0, 60.0], (n, 1))
    inten = rng.uniform(0, scale, n) * (rng.random(n) > 0.2)
    scan = Scan(np.column_stack([xyz, inten]).astype(np.float32), intensity_scale=scale,
                semantic=rng.integers(0, 100, n))
    ground = rng.random(n) < 0.7
    sensor = replace(KITTI, intensity_scale=scale)
    out, info = W.apply(scan, {"water_height_mm": h, "noise_floor": nf}, sensor, RNG(seed + 1), ground=ground,
                        fidelity={"fit_points": fit_points, "range_bins": range_bins}, return_info=True)
    kept = ~info["lost"]
    assert np.all(np.isfinite(out.points))
    assert np.array_equal(out.xyz, scan.xyz[kept])  # ranges neither grow nor shrink
    assert np.all((out.intensity >= 0) & (out.intensity <= scale))
    assert np.all(out.intensity <= scan.intensity[kept])
    assert not info["lost"][~ground].any()
    assert np.array_equal(out.semantic, scan.semantic[kept])


def test_accuracy_time_curve_rows(sweep):
    scan, _ = sweep
    rows = W.accuracy_time_curve(scan, KITTI, "heavy", seeds=[0], repeats=1)
    assert {r["knob"] for r in rows} == set(W.FIDELITY_LEVELS)
    top = [r for r in rows if r["knob"] == "range_bins" and r["value"] == W.HIGHEST_FIDELITY["range_bins"]][0]
    assert top["err_lost"] == 0.0 and top["err_mean_shift"] == 0.0
    assert all(r["time_s"] > 0 and np.isfinite(r["err_lost"]) for r in rows)
