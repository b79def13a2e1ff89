"""Rain effect (LISA model): Mie optics, drop sampling, contract and edge cases.

The contract runs on a synthetic full sweep; shares of affected returns stated for
real KITTI scans (and how their zero-remission returns fare) are checked on them."""

from __future__ import annotations


import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omnilidar.domains.effects import rain
from omnilidar.domains.effects._mie import mie_efficiencies
from omnilidar.domains.effects.base import WEATHER_RETURN_LABEL
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Boxes, Scan
from omnilidar.lidar.sensors import PRESETS

from real_samples import real_file
KITTI = PRESETS["kitti_hdl64e"]
NUSC = PRESETS["nuscenes_hdl32e"]


def _real_kitti_scan(name: str = "000001") -> Scan:
    return _labelled(np.fromfile(real_file(f"kitti_object/velodyne/{name}.bin"), np.float32).reshape(-1, 4))


@pytest.fixture(scope="module")
def sweep(synthetic_sweep) -> Scan:
    """A full synthetic HDL-64E sweep with simple labels."""
    return _labelled(synthetic_sweep.points)


def _labelled(pts: np.ndarray) -> Scan:
    n = len(pts)
    sem = np.full(n, 40, np.uint16)
    inst = (np.arange(n) % 7).astype(np.uint16)
    ring = (np.arange(n) % 64).astype(np.int16)
    boxes = Boxes(np.array([[10, 0, -1, 4, 2, 1.5, 0.1]], np.float32), np.array(["Car"]))
    return Scan(pts, sem, inst, ring, boxes)


def _ranges(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, :3].astype(np.float64), axis=1)


def _beams(n, r_lo, r_hi, remission, rng):
    """n returns at ranges uniform in [r_lo, r_hi], random near-horizontal directions."""
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(-0.2, 0.05, n)
    r = rng.uniform(r_lo, r_hi, n)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    return np.column_stack([d * r[:, None], np.broadcast_to(remission, (n,))]).astype(np.float32)


# ------------------------------------------------------------------ Mie optics

# Wiscombe's MIEV0 reference cases: (x, m, Q_ext, Q_sca)
MIEV0 = [
    (0.099, 0.75, 7.417859e-06, 7.417859e-06),
    (10.0, 0.75, 2.232265, 2.232265),
    (1000.0, 0.75, 1.997908, 1.997908),
    (100.0, 1.33 + 1e-5j, 2.101321, 2.096594),
    (10000.0, 1.33 + 1e-5j, 2.004089, 1.723857),
    (0.055, 1.5 + 1j, 0.101491, 1.131687e-05),
    (100.0, 1.5 + 1j, 2.097502, 1.283697),
]


@pytest.mark.parametrize("x,m,q_ext,q_sca", MIEV0)
def test_mie_matches_miev0_reference(x, m, q_ext, q_sca):
    e, s, _ = mie_efficiencies([x], m)
    assert e[0] == pytest.approx(q_ext, rel=2e-6)
    assert s[0] == pytest.approx(q_sca, rel=2e-6)


def test_mie_backscatter_matches_miev0_s1():
    # Q_back = |2 S1(180 deg) / x|^2 with MIEV0's S1 for cases 7 and 8.
    for x, s1 in ((10.0, -1.07857 - 3.60881e-2j), (1000.0, 1.70578e1 + 4.84251e2j)):
        assert mie_efficiencies([x], 0.75)[2][0] == pytest.approx(abs(2 * s1 / x) ** 2, rel=1e-4)


def test_mie_rayleigh_and_large_sphere_limits():
    m = rain.M_WATER
    x = np.array([1e-3, 5e-3])
    _, q_sca, _ = mie_efficiencies(x, m)
    rayleigh = 8.0 / 3.0 * x**4 * abs((m**2 - 1) / (m**2 + 2)) ** 2
    np.testing.assert_allclose(q_sca, rayleigh, rtol=1e-4)
    # Large drops: Q_ext -> 2, the ripple-averaged excess follows the edge term.
    x = np.linspace(2000.0, 2100.0, 200)
    q_ext = mie_efficiencies(x, m)[0]
    assert abs(q_ext.mean() - 2.0) < 0.02
    edge = rain.EDGE_COEFF * 2050.0 ** (-2.0 / 3.0)
    assert (q_ext.mean() - 2.0) == pytest.approx(edge, rel=0.05)


@pytest.mark.parametrize("rate,measured", [(5.0, 0.001), (100.0, 0.0067), (2500.0, 0.05)])
def test_extinction_matches_measured(rate, measured):
    alpha = rain.extinction_coefficient(rate)
    assert alpha == pytest.approx(measured, rel=0.02)
    # and the geometric-optics closed form pi N0 / Lambda^3 (Q_ext = 2, no cut)
    lam = rain.marshall_palmer_lambda(rate)
    assert alpha == pytest.approx(np.pi * rain.MP_N0 * 1e-6 / lam**3, rel=0.02)
    assert rain.extinction_coefficient(0.0) == 0.0


# ------------------------------------------------------------------- contract


def test_zero_rate_and_empty_scan_return_input(sweep):
    scan = sweep
    assert rain.apply(scan, {"rate_mm_h": 0.0}, KITTI, np.random.default_rng(0)) is scan
    out, info = rain.apply(scan, {"rate_mm_h": 0.0}, KITTI, np.random.default_rng(0), return_info=True)
    assert out is scan and not info["lost"].any() and not info["changed"].any() and not info["weather"].any()
    empty = Scan(np.zeros((0, 4), np.float32))
    assert rain.apply(empty, {"rate_mm_h": 100.0}, KITTI, np.random.default_rng(0)) is empty


def test_deterministic_for_a_seed_and_input_untouched(sweep):
    scan = sweep
    before = scan.points.copy()
    a = rain.apply(scan, {"rate_mm_h": 300.0}, KITTI, np.random.default_rng(7))
    b = rain.apply(scan, {"rate_mm_h": 300.0}, KITTI, np.random.default_rng(7))
    c = rain.apply(scan, {"rate_mm_h": 300.0}, KITTI, np.random.default_rng(8))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.semantic, b.semantic)
    assert not np.array_equal(a.points, c.points)
    assert np.array_equal(scan.points, before)


def test_labels_rings_boxes_and_info_are_consistent(sweep):
    scan = sweep
    out, info = rain.apply(scan, {"rate_mm_h": 1500.0}, KITTI, np.random.default_rng(1), return_info=True)
    keep = ~info["lost"]
    assert len(out) == keep.sum() and info["weather"].shape == (len(out),)
    assert info["weather"].any()
    w = info["weather"]
    assert np.all(out.semantic[w] == WEATHER_RETURN_LABEL) and np.all(out.instance[w] == 0)
    assert np.array_equal(out.semantic[~w], scan.semantic[keep][~w])
    assert np.array_equal(out.instance[~w], scan.instance[keep][~w])
    assert np.array_equal(out.ring, scan.ring[keep])
    assert out.boxes is scan.boxes
    # changed = kept and something differs; unchanged kept points are bit-identical
    same = np.all(out.points == scan.points[keep], axis=1)
    assert np.array_equal(info["changed"][keep], ~same | w)
    assert not info["changed"][info["lost"]].any()


def test_points_stay_on_their_ray_and_never_beyond_the_target(sweep):
    scan = sweep
    out, info = rain.apply(scan, {"rate_mm_h": 2500.0}, KITTI, np.random.default_rng(2), return_info=True)
    src = scan.points[~info["lost"]]
    r_in, r_out = _ranges(src), _ranges(out.points)
    assert np.all(r_out <= r_in) and np.all(r_out > 0)
    cos = np.einsum("ij,ij->i", src[:, :3].astype(np.float64), out.points[:, :3]) / (r_in * r_out)
    assert np.all(cos > 1 - 1e-6)
    w = info["weather"]
    assert np.all(r_out[w] >= KITTI.min_range * (1 - 1e-6))
    # kept targets move only by the bounded rain jitter (<= 3 sigma_max)
    assert np.all(r_in[~w] - r_out[~w] <= 3 * KITTI.range_noise_std + 1e-4)
    rain_i = out.points[w, 3]
    assert np.all((rain_i >= 0) & (rain_i <= rain.RHO_WATER + 1e-7))


def test_kept_intensity_is_exactly_two_way_attenuated(sweep):
    scan = sweep
    rate = 400.0
    out, info = rain.apply(scan, {"rate_mm_h": rate}, KITTI, np.random.default_rng(3), return_info=True)
    alpha = rain.extinction_coefficient(rate)
    src = scan.points[~info["lost"]][~info["weather"]]
    expect = src[:, 3].astype(np.float64) * np.exp(-2 * alpha * _ranges(src))
    np.testing.assert_allclose(out.points[~info["weather"], 3], expect, rtol=1e-6, atol=1e-7)


def _affected_and_shift(scan: Scan) -> list[float]:
    """Share of lost or rain returns per severity; checks both it and the intensity drop grow."""
    affected, shift = [], []
    for sev in ("light", "moderate", "heavy"):
        out, info = rain.apply(scan, rain.nominal_params(sev), KITTI, np.random.default_rng(4), return_info=True)
        summary = rain.fidelity_summary(scan, out, info, KITTI)
        affected.append(summary["frac_lost"] + summary["frac_rain"])
        shift.append(summary["mean_intensity_shift"])
    assert affected[0] < affected[1] < affected[2]
    assert shift[0] > shift[1] > shift[2]
    return affected


def test_heavier_rain_affects_more_points(sweep):
    _affected_and_shift(sweep)


def test_share_of_real_kitti_rain_affects():
    affected = _affected_and_shift(_real_kitti_scan())
    assert 0.01 < affected[0] and affected[2] < 0.4


def _trace_rain_losses(scan: Scan) -> np.ndarray:
    """Trace rain: the only losses are returns whose clean power sits within the
    attenuation of the floor. Returns the lost mask."""
    rate = 0.01
    out, info = rain.apply(scan, {"rate_mm_h": rate}, KITTI, np.random.default_rng(5), return_info=True)
    r = _ranges(scan.points)
    rho = np.where(scan.points[:, 3] > 0, scan.points[:, 3], rain.ZERO_REMISSION_REFLECTANCE)
    floor = rain.FLOOR_REFLECTANCE / np.maximum(KITTI.max_range, r) ** 2
    margin = rho / r**2 / floor
    atten = np.exp(-2 * rain.extinction_coefficient(rate) * r)
    assert np.all(margin[info["lost"]] * atten[info["lost"]] < 1)
    return info["lost"]


def test_only_what_rain_reaches(sweep):
    _trace_rain_losses(sweep)


def test_trace_rain_keeps_real_kitti_and_its_zero_remission_returns():
    # Trace rain: (almost) no clean return is lost; LISA loses every
    # zero-remission point (8.5 % of this scan) at any rate.
    scan = _real_kitti_scan()
    lost = _trace_rain_losses(scan)
    zero = scan.points[:, 3] == 0
    assert zero.mean() > 0.05 and lost[zero].mean() < 1e-3 and lost.mean() < 1e-4


def test_returns_at_the_origin_or_inside_the_minimum_range_get_no_drops():
    # A return at the origin and returns inside the minimum range get no drops.
    pts = np.array([[0, 0, 0, 0.5], [1.0, 0.2, 0, 0.3], [0.5, 0, 0, 0.0]], np.float32)
    tiny = Scan(pts, np.array([40, 40, 40], np.uint16))
    out, info = rain.apply(tiny, {"rate_mm_h": 2500.0}, KITTI, np.random.default_rng(0), return_info=True)
    assert not info["lost"].any() and not info["weather"].any()
    assert np.array_equal(out.points[0], pts[0])  # r = 0: nothing to attenuate
    assert np.all(out.points[1:, 3] <= pts[1:, 3])


# --------------------------------------------------- drop sampling correctness


def test_restricted_sampling_matches_brute_force_drops():
    """Our restricted Poisson sampling vs sampling every drop of every beam."""
    rng = np.random.default_rng(11)
    n, r_t, rho, rate = 4000, 20.0, 0.02, 200.0
    pts = _beams(n, r_t, r_t, rho, rng)
    out, info = rain.apply(Scan(pts), {"rate_mm_h": rate}, KITTI, np.random.default_rng(12), return_info=True)
    ours = info["weather"].mean()
    ours_r = _ranges(out.points[info["weather"]])

    alpha = rain.extinction_coefficient(rate)
    lam = rain.marshall_palmer_lambda(rate)  # per mm
    t = np.tan(KITTI.beam_divergence_mrad * 1e-3)
    r0 = KITTI.min_range
    dmax = rain.D_MAX_MM
    per_m3 = rain.MP_N0 / lam * (1 - np.exp(-lam * dmax))
    vol = np.pi * t**2 / 12.0 * (r_t**3 - r0**3)
    k = rng.poisson(per_m3 * vol, n)
    r = np.cbrt(r0**3 + rng.random(k.sum()) * (r_t**3 - r0**3))  # uniform in the frustum
    d = -np.log1p(-rng.random(k.sum()) * (1 - np.exp(-lam * dmax))) / lam * 1e-3  # m
    p = rain.RHO_WATER * np.exp(-2 * alpha * r) * np.minimum((d / (t * r)) ** 2, 1) / r**2
    owner = np.repeat(np.arange(n), k)
    best = np.full(n, -1.0)
    np.maximum.at(best, owner, p)
    p_t = rho * np.exp(-2 * alpha * r_t) / r_t**2
    floor = rain.FLOOR_REFLECTANCE / KITTI.max_range**2
    brute = best > max(p_t, floor)
    se = np.sqrt(2 * brute.mean() * (1 - brute.mean()) / n)
    assert 0.1 < brute.mean() < 0.9
    assert abs(ours - brute.mean()) < 4 * se
    # range of the winning drop: same distribution
    win = np.zeros(n)
    order = np.lexsort((-p, owner))
    first = order[np.unique(owner[order], return_index=True)[1]]
    win[owner[first]] = r[first]
    from scipy.stats import ks_2samp

    assert ks_2samp(ours_r, win[brute]).pvalue > 1e-3


def test_zero_remission_is_treated_as_below_the_lowest_reported_level():
    """A zero-remission return behaves exactly like one of reflectance
    ZERO_REMISSION_REFLECTANCE (half KITTI's lowest routine level) in the power
    comparison, keeps intensity 0, and is not lost merely for being zero."""
    rng = np.random.default_rng(21)
    n = 6000
    zero_pts = _beams(n, 30, 75, 0.0, rng)
    twin = zero_pts.copy()
    twin[:, 3] = rain.ZERO_REMISSION_REFLECTANCE
    for rate in (0.5, 300.0, 2500.0):
        fates = []
        for pts in (zero_pts, twin):
            out, info = rain.apply(Scan(pts), {"rate_mm_h": rate}, KITTI, np.random.default_rng(22), return_info=True)
            fates.append((info["lost"], out.points[:, :3], info["weather"]))
            if pts is zero_pts:
                assert np.all(out.points[~info["weather"], 3] == 0)
        # same draws, same decisions, same geometry (float32(0.02) != 0.02: allclose)
        assert np.array_equal(fates[0][0], fates[1][0]) and np.array_equal(fates[0][2], fates[1][2])
        np.testing.assert_allclose(fates[0][1], fates[1][1], rtol=1e-5, atol=1e-5)
        assert fates[0][0].mean() < 0.01  # LISA: all lost


def test_real_zero_remission_rained_like_the_dimmest_reported_returns():
    """On real KITTI scans zeros turn into rain returns at about the rate of
    the dimmest nonzero returns (<= 0.05) at the same range, not all-or-nothing."""
    rain_zero, rain_low, lost = [], [], []
    for name in ("000000", "000001"):
        scan = _real_kitti_scan(name)
        r = _ranges(scan.points)
        out, info = rain.apply(scan, {"rate_mm_h": 100.0}, KITTI, np.random.default_rng(6), return_info=True)
        weather = np.zeros(len(scan), bool)
        weather[~info["lost"]] = info["weather"]
        band = (r > 20) & (r < 60)
        i = scan.points[:, 3]
        rain_zero.append(weather[band & (i == 0)])
        rain_low.append(weather[band & (i > 0) & (i <= 0.05)])
        lost.append(info["lost"][band & (i == 0)])
    z, low = np.concatenate(rain_zero), np.concatenate(rain_low)
    assert len(z) > 1000 and len(low) > 80
    assert 0.5 < z.mean() / low.mean() < 2.0, (z.mean(), low.mean())
    assert np.concatenate(lost).mean() < 0.01


# ----------------------------------------------------------- stability, input


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 40),
    seed=st.integers(0, 2**31 - 1),
    rate=st.one_of(st.just(0.0), st.floats(1e-3, 5000.0)),
    nusc=st.booleans(),
)
def test_property_finite_bounded_outputs(n, seed, rate, nusc):
    sensor = NUSC if nusc else KITTI
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * rng.choice([1e-6, 0.5, 3.0, 40.0, 150.0], size=(n, 1))
    xyz[rng.random(n) < 0.1] = 0.0
    inten = rng.choice([0.0, 1.0, 0.01], size=n) * rng.random(n) * sensor.intensity_scale
    inten[rng.random(n) < 0.2] = 0.0
    pts = np.column_stack([xyz, inten]).astype(np.float32)
    scan = Scan(pts, np.full(n, 10, np.uint16))
    out, info = rain.apply(scan, {"rate_mm_h": rate}, sensor, np.random.default_rng(seed), return_info=True)
    assert np.all(np.isfinite(out.points))
    keep = ~info["lost"]
    assert len(out) == keep.sum()
    r_in, r_out = _ranges(pts[keep]), _ranges(out.points)
    assert np.all(r_out <= r_in)
    assert np.all((r_out > 0) | (r_in == 0))
    assert np.all((out.points[:, 3] >= 0) & (out.points[:, 3] <= sensor.intensity_scale))


def test_bad_input_raises_input_error():
    scan = Scan(np.array([[1, 2, 3, 0.5]], np.float32))
    g = np.random.default_rng(0)
    for params in ({"rate_mm_h": -1.0}, {"rate_mm_h": float("nan")}, {"rate": 5.0}, {"rate_mm_h": "x"}, {}):
        with pytest.raises(InputError):
            rain.apply(scan, params, KITTI, g)
    with pytest.raises(InputError):
        rain.apply(scan, {"rate_mm_h": 5.0}, KITTI, g, fidelity={"bogus": 1})
    with pytest.raises(InputError):
        rain.apply(scan, {"rate_mm_h": 5.0}, KITTI, g, fidelity={"radial_nodes": 1})
    bad = Scan(np.array([[np.nan, 0, 0, 0.1]], np.float32))
    with pytest.raises(InputError):
        rain.apply(bad, {"rate_mm_h": 5.0}, KITTI, g)
    with pytest.raises(InputError):
        rain.draw_params("drizzle", g)


def test_draw_params_in_band_and_reproducible():
    for sev, spec in rain.SEVERITIES.items():
        lo, hi = spec["rate_mm_h"]
        draws = [rain.draw_params(sev, np.random.default_rng(s))["rate_mm_h"] for s in range(50)]
        assert all(lo <= d <= hi for d in draws)
        assert rain.draw_params(sev, np.random.default_rng(3)) == rain.draw_params(sev, np.random.default_rng(3))
    assert rain.NEEDS_GROUND is False
    assert set(rain.DEFAULT_FIDELITY) == set(rain.FIDELITY_LEVELS)


def test_accuracy_time_curve_rows():
    rng = np.random.default_rng(0)
    scan = Scan(_beams(1500, 5, 70, 0.1, rng))
    rows = rain.accuracy_time_curve(scan, KITTI, "moderate", seeds=[0, 1])
    assert len(rows) == sum(len(v) for v in rain.FIDELITY_LEVELS.values())
    for row in rows:
        assert row["seconds"] > 0 and np.isfinite(row["err_frac_rain"]) and row["alpha"] > 0
