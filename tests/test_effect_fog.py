"""Fog effect: core formulas, severity ordering, locality, determinism and edge cases.

Contract checks run on a synthetic full sweep; the shares of fogged and lost returns
stated for real KITTI geometry are checked on the real scans."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from omnilidar.domains.effects import fog
from omnilidar.domains.effects.base import WEATHER_RETURN_LABEL
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Boxes, Scan
from omnilidar.lidar.sensors import PRESETS

from real_samples import real_file
KITTI = PRESETS["kitti_hdl64e"]
NUSC = PRESETS["nuscenes_hdl32e"]


def _kitti(name: str = "000001") -> np.ndarray:
    return np.fromfile(real_file(f"kitti_object/velodyne/{name}.bin"), np.float32).reshape(-1, 4)


def _labelled(pts: np.ndarray) -> Scan:
    """A sweep's points with simple labels, instances, rings and one box."""
    n = len(pts)
    boxes = Boxes(np.array([[10, 2, -1, 4, 2, 1.5, 0.3]], np.float32), np.array(["Car"]), np.array([7]))
    return Scan(
        pts,
        semantic=np.full(n, 40, np.uint16),
        instance=(np.arange(n) % 5).astype(np.uint16),
        ring=(np.arange(n) % 64).astype(np.int16),
        boxes=boxes,
    )


@pytest.fixture(scope="module")
def kitti_scan(synthetic_sweep) -> Scan:
    """A full synthetic HDL-64E sweep (its intensities: KITTI's 0..0.99 with exact zeros)."""
    return _labelled(synthetic_sweep.points)


@pytest.fixture(scope="module")
def real_kitti_scan() -> Scan:
    return _labelled(_kitti())


def _few_points() -> np.ndarray:
    """Ten returns at 5-30 m (input validation needs no real scan)."""
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(10, 3)) * [1, 1, 0.05]
    xyz *= (rng.uniform(5, 30, 10) / np.linalg.norm(xyz, axis=1))[:, None]
    return np.column_stack([xyz, rng.uniform(0, 1, 10)]).astype(np.float32)


def _run(scan, alpha, beta, seed=0, jitter=1.0, sensor=KITTI, **kw):
    return fog.apply(scan, {"alpha": alpha, "beta": beta, "range_jitter": jitter}, sensor,
                     np.random.default_rng(seed), return_info=True, **kw)


# ------------------------------------------------------------------ core formulas


@pytest.mark.parametrize("alpha", [0.0, 0.06, 0.5])
@pytest.mark.parametrize("r", [0.95, 1.5, 4.64, 7.0, 12.0])
def test_soft_echo_matches_adaptive_quadrature(alpha, r):
    def integrand(t):  # the anchor's form: integral over time of pulse * fog profile
        rp = r - fog.SPEED_OF_LIGHT * t / 2
        return np.sin(np.pi * t / (2 * fog.TAU_H)) ** 2 * fog._fog_profile(np.array([rp]), alpha)[0]

    kink = [2 * (r - x) / fog.SPEED_OF_LIGHT for x in (fog.OVERLAP_START, fog.OVERLAP_FULL)]
    kink = [k for k in kink if 0 < k < 2 * fog.TAU_H]
    ref = quad(integrand, 0, 2 * fog.TAU_H, points=kink or None, epsabs=0, epsrel=1e-12, limit=200)[0]
    got = fog.soft_echo(np.array([r]), alpha, quad_nodes=32)[0]
    assert got == pytest.approx(ref, rel=1e-9)


def test_soft_echo_vanishes_before_overlap():
    r = np.array([0.0, 0.3, 0.9])
    assert np.all(fog.soft_echo(r, 0.03) == 0.0)
    assert fog.soft_echo(np.array([0.95]), 0.03)[0] > 0


@pytest.mark.parametrize("alpha", [a for a in fog.ALPHAS if a > 0])
def test_table_peak_and_interval(alpha):
    t = fog.soft_return_table(alpha)
    assert 4.6 <= t.peak_range <= 4.72  # "about 4.6-4.7 m" (the anchor's figure)
    np.testing.assert_allclose(t.r_fog, np.minimum(t.r0, t.peak_range))
    live = t.i_fog > 0
    assert np.all(t.r_lo[live] > fog.OVERLAP_START - 1e-12)
    assert np.all((t.r_lo <= t.r_fog) & (t.r_fog <= t.r_hi) & (t.r_hi <= t.r0 + 1e-12))
    # saturated beyond the whole echo: constant from ~7 m on
    sat = t.r0 >= 7.0
    assert np.ptp(t.i_fog[sat]) == 0 and np.ptp(t.r_lo[sat]) == 0 and np.ptp(t.r_hi[sat]) == 0
    # i_fog is the strongest untruncated echo in front of the target: the curve up to the
    # peak, then the peak value; the grid never beats the refined peak
    nodes = fog.DEFAULT_FIDELITY["quad_nodes"]
    curve = fog.soft_echo(t.r0, alpha, nodes)
    peak_value = fog.soft_echo(np.array([t.peak_range]), alpha, nodes)[0]
    np.testing.assert_allclose(t.i_fog, np.where(t.r0 < t.peak_range, curve, peak_value), rtol=1e-12)
    assert curve.max() <= peak_value * (1 + 1e-12)


def test_denser_fog_weakens_and_pulls_echo_closer():
    a, b = fog.soft_return_table(0.005), fog.soft_return_table(0.06)
    assert b.i_fog[-1] < a.i_fog[-1] and b.peak_range < a.peak_range


def test_hard_attenuation_hand_computed():
    scan = Scan(np.array([[6.0, 8.0, 0.0, 0.5]], np.float32))  # R0 = 10 m
    out, info = _run(scan, alpha=0.03, beta=0.0)
    assert out.points[0, 3] == np.float32(np.float32(0.5) * np.exp(-0.6))
    assert np.array_equal(out.points[:, :3], scan.points[:, :3])
    assert info["changed"].tolist() == [True] and not info["weather"].any() and not info["lost"].any()


@pytest.mark.parametrize("alpha", [0.01, 0.06])
def test_fog_decision_threshold(alpha):
    r0 = 30.0
    i_fog = fog.soft_return_table(alpha).i_fog[-1]
    beta_star = fog.BETA0 * np.exp(-2 * alpha * r0) / (i_fog * r0**2)  # I_soft == I_hard
    scan = Scan(np.array([[0.0, r0, 0.0, 0.4]], np.float32))
    above, info_a = _run(scan, alpha, 1.001 * beta_star, jitter=0.0)
    below, info_b = _run(scan, alpha, 0.999 * beta_star, jitter=0.0)
    assert info_a["weather"].tolist() == [True] and info_b["weather"].tolist() == [False]
    # fog return: at R_fog on the same beam, intensity I_soft (r_fog / R0)^2
    t = fog.soft_return_table(alpha)
    assert np.linalg.norm(above.points[0, :3]) == pytest.approx(t.peak_range, rel=1e-6)
    assert above.points[0, 0] == 0 and above.points[0, 1] > 0
    expect = i_fog * 1.001 * beta_star / fog.BETA0 * 0.4 * t.peak_range**2
    assert above.points[0, 3] == pytest.approx(expect, rel=1e-5)
    assert below.points[0, 3] == pytest.approx(0.4 * np.exp(-2 * alpha * r0), rel=1e-6)


def test_detection_floor_loses_only_weak_returns():
    # floor = min(q/2 / max_range^2, weakest clear return); q = 0.01 here
    pts = np.array([[0, 70, 0, 0.01], [0, 2, 0, 0.5], [0, 20, 0, 0.3]], np.float32)
    floor = min(0.005 / KITTI.max_range**2, 0.01 / 70**2)
    out, info = _run(Scan(pts), alpha=0.02, beta=0.0)
    expect_lost = pts[:, 3] * np.exp(-0.04 * np.linalg.norm(pts[:, :3], axis=1)) < floor * np.sum(pts[:, :3] ** 2, 1)
    assert info["lost"].tolist() == expect_lost.tolist() == [True, False, False]
    assert len(out) == 2


# ------------------------------------------------------------------ full sweeps


def _affected_counts(scan: Scan) -> dict:
    """(fogged, fogged or lost) returns per (severity, alpha); checks they grow with both."""
    affected = {}
    for sev, spec in fog.SEVERITIES.items():
        for alpha in fog.ALPHAS[1:]:
            _, info = _run(scan, alpha, spec["beta"])
            fogged = np.zeros(len(scan), bool)
            fogged[~info["lost"]] = info["weather"]
            affected[sev, alpha] = (fogged.sum(), (fogged | info["lost"]).sum())
    sevs, alphas = list(fog.SEVERITIES), fog.ALPHAS[1:]
    for a in alphas:
        assert [affected[s, a][0] for s in sevs] == sorted(affected[s, a][0] for s in sevs)
        assert [affected[s, a][1] for s in sevs] == sorted(affected[s, a][1] for s in sevs)
    for s in sevs:
        assert [affected[s, a][1] for a in alphas] == sorted(affected[s, a][1] for a in alphas)
    return affected


def test_monotone_in_severity_and_alpha(kitti_scan):
    _affected_counts(Scan(kitti_scan.points))


@pytest.mark.parametrize("name", ["000000", "000001"])
def test_fogged_share_on_real_kitti(name):
    scan = Scan(_kitti(name))
    affected = _affected_counts(scan)
    assert affected["heavy", 0.06][0] > 0.1 * len(scan) > affected["light", 0.005][0]


def test_only_what_fog_reaches(kitti_scan):
    out, info = _run(kitti_scan, 0.03, 0.05)
    kept = ~info["lost"]
    src = kitti_scan.points[kept]
    weather = info["weather"]
    hard = ~weather
    # hard returns keep geometry and labels; only intensity is scaled by the transmission
    assert np.array_equal(out.points[hard, :3], src[hard, :3])
    assert np.array_equal(out.semantic[hard], kitti_scan.semantic[kept][hard])
    assert np.array_equal(out.instance[hard], kitti_scan.instance[kept][hard])
    r = np.linalg.norm(src[hard, :3].astype(np.float64), axis=1)
    np.testing.assert_allclose(out.points[hard, 3], src[hard, 3] * np.exp(-0.06 * r), rtol=1e-6)
    # zero-intensity hard returns are bit-for-bit untouched
    zero = hard & (src[:, 3] == 0)
    assert zero.any() and np.array_equal(out.points[zero], src[zero])
    assert not info["changed"][kept][zero].any()
    # info["changed"] is exactly "kept and different"
    diff = np.any(out.points != src, axis=1) | (out.semantic != kitti_scan.semantic[kept])
    assert np.array_equal(info["changed"][kept], diff) and not info["changed"][~kept].any()
    # fog returns: labelled as weather, same ring, in front of their target
    assert np.all(out.semantic[weather] == WEATHER_RETURN_LABEL) and np.all(out.instance[weather] == 0)
    assert np.array_equal(out.ring, kitti_scan.ring[kept])
    assert out.boxes is kitti_scan.boxes


def _check_attenuation_only(scan: Scan) -> tuple[np.ndarray, dict]:
    out, info = _run(scan, 0.06, 0.0)
    assert not info["weather"].any()
    assert np.array_equal(out.semantic, scan.semantic[~info["lost"]])
    # losses grow with extinction
    _, light = _run(scan, 0.01, 0.0)
    assert light["lost"].sum() < info["lost"].sum() and not (light["lost"] & ~info["lost"]).any()
    return out, info


def test_beta_zero_is_attenuation_only(kitti_scan):
    _check_attenuation_only(kitti_scan)


def test_beta_zero_loses_few_far_returns_of_real_kitti(real_kitti_scan):
    _, info = _check_attenuation_only(real_kitti_scan)
    # losses are far, dim returns
    r = np.linalg.norm(real_kitti_scan.points[:, :3], axis=1)
    assert 0 < info["lost"].mean() < 0.1 and r[info["lost"]].min() > 20.0


def test_zero_alpha_returns_input(kitti_scan):
    for beta in (0.0, 0.2):
        out = fog.apply(kitti_scan, {"alpha": 0.0, "beta": beta}, KITTI, np.random.default_rng(0))
        assert out is kitti_scan
    out, info = _run(kitti_scan, 0.0, 0.2)
    assert out is kitti_scan and np.array_equal(out.points, kitti_scan.points)
    assert not (info["lost"].any() or info["changed"].any() or info["weather"].any())


def test_deterministic_for_seed(kitti_scan):
    a, _ = _run(kitti_scan, 0.02, 0.2, seed=3)
    b, _ = _run(kitti_scan, 0.02, 0.2, seed=3)
    c, info = _run(kitti_scan, 0.02, 0.2, seed=4)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.semantic, b.semantic)
    assert not np.array_equal(a.points[info["weather"]], c.points[info["weather"]])
    # the jitter moves fog returns only, inside the echo's half-power interval
    t = fog.soft_return_table(0.02)
    rng_ = np.linalg.norm(c.points[info["weather"], :3], axis=1)
    assert rng_.min() >= t.r_lo[-1] - 1e-4 and rng_.max() <= t.r_hi[-1] + 1e-4


def test_does_not_mutate_input(kitti_scan):
    before = kitti_scan.points.copy(), kitti_scan.semantic.copy()
    _run(kitti_scan, 0.06, 0.2)
    assert np.array_equal(kitti_scan.points, before[0]) and np.array_equal(kitti_scan.semantic, before[1])


def test_nuscenes_scale_stays_in_range(synthetic_nuscenes_sweep):
    raw = synthetic_nuscenes_sweep.points
    scan = Scan(raw, intensity_scale=255.0)
    out, info = _run(scan, 0.06, 0.2, sensor=NUSC)
    assert info["weather"].any()
    assert out.points[:, 3].min() >= 0 and out.points[:, 3].max() <= 255.0
    kept = ~info["lost"]
    assert np.all(out.points[:, 3] <= raw[kept, 3] + 255.0 * (info["weather"]))


# ------------------------------------------------------------------ edge cases


def _check_sane(scan, out, info, scale=1.0):
    kept = ~info["lost"]
    assert len(info["lost"]) == len(scan) == len(info["changed"]) and len(info["weather"]) == len(out)
    assert np.all(np.isfinite(out.points))
    r_in = np.linalg.norm(scan.points[kept, :3], axis=1)
    r_out = np.linalg.norm(out.points[:, :3], axis=1)
    assert np.all(r_out <= r_in) and np.all(r_out[r_in > 0] > 0)
    assert np.all(r_out[info["weather"]] > fog.OVERLAP_START - 1e-4)
    assert out.points[:, 3].min(initial=0) >= 0 and out.points[:, 3].max(initial=0) <= scale


def test_edge_cases():
    empty = Scan(np.zeros((0, 4), np.float32))
    out, info = _run(empty, 0.06, 0.2)
    assert out is empty and len(info["weather"]) == 0
    tricky = np.array([
        [0, 0, 0, 0.5],  # at the sensor
        [1e-20, 0, 0, 0.0],  # ~0 range, zero intensity
        [0.5, 0, 0, 0.3],  # inside the overlap dead zone
        [0, 0, 60, 0.0],  # far, zero intensity
        [3e4, 0, 0, 1.0],  # absurdly far
    ], np.float32)
    for pts in (tricky, tricky[:1], tricky[3:4], tricky * [1, 1, 1, 0]):
        scan = Scan(pts)
        out, info = _run(scan, 0.06, 0.2)
        _check_sane(scan, out, info)
    out, info = _run(Scan(tricky), 0.06, 0.2)
    assert np.array_equal(out.points[0], tricky[0])  # R0 = 0: nothing to attenuate
    assert not info["weather"][:3].any()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    xyz=st.lists(st.tuples(*[st.floats(-120, 120, width=32)] * 3), min_size=1, max_size=40),
    inten=st.data(),
    alpha=st.floats(0, 1),
    beta=st.floats(0, 2),
    jitter=st.floats(0, 1),
    scale=st.sampled_from([1.0, 255.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_property_sane_outputs(xyz, inten, alpha, beta, jitter, scale, seed):
    n = len(xyz)
    i = inten.draw(st.lists(st.floats(0, scale, width=32), min_size=n, max_size=n))
    pts = np.column_stack([np.asarray(xyz, np.float32), np.asarray(i, np.float32)])
    scan = Scan(pts, semantic=np.full(n, 9, np.uint16), intensity_scale=scale)
    # Effects work in the sensor's intensity scale (one rule for all effects).
    out, info = _run(scan, alpha, beta, seed=seed, jitter=jitter, sensor=dataclasses.replace(KITTI, intensity_scale=scale))
    _check_sane(scan, out, info, scale)
    assert np.all(out.semantic[info["weather"]] == WEATHER_RETURN_LABEL)
    assert np.all(out.semantic[~info["weather"]] == 9)


# ------------------------------------------------------------------ interface


def test_draw_params():
    for sev, spec in fog.SEVERITIES.items():
        seen = set()
        for seed in range(40):
            p = fog.draw_params(sev, np.random.default_rng(seed))
            assert p == fog.draw_params(sev, np.random.default_rng(seed))
            assert p["beta"] == spec["beta"] and p["alpha"] in fog.ALPHAS
            json.dumps(p)
            seen.add(p["alpha"])
        assert seen == set(fog.ALPHAS)
    assert fog.NEEDS_GROUND is False
    assert set(fog.SEVERITIES) == {"light", "moderate", "heavy"}
    assert all(fog.DEFAULT_FIDELITY[k] in v for k, v in fog.FIDELITY_LEVELS.items())


@pytest.mark.parametrize("params", [
    {"alpha": -0.1, "beta": 0.1}, {"alpha": float("nan"), "beta": 0.1}, {"alpha": 0.1},
    {"alpha": 0.1, "beta": 0.1, "density": 3}, {"alpha": "thick", "beta": 0.1},
    {"alpha": 0.1, "beta": 0.1, "range_jitter": 2.0},
])
def test_bad_params(params):
    with pytest.raises(InputError):
        fog.apply(Scan(_few_points()), params, KITTI, np.random.default_rng(0))


def test_bad_inputs():
    with pytest.raises(InputError):
        fog.draw_params("apocalyptic", np.random.default_rng(0))
    with pytest.raises(InputError):
        fog.apply(Scan(_few_points()), {"alpha": 0.1, "beta": 0.1}, KITTI, np.random.default_rng(0),
                  fidelity={"quad_nodes": 0})
    with pytest.raises(InputError, match="fidelity"):
        fog.apply(Scan(_few_points()), {"alpha": 0.1, "beta": 0.1}, KITTI, np.random.default_rng(0),
                  fidelity={"steps": 3})
    bad = _few_points().copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        fog.apply(Scan(bad), {"alpha": 0.1, "beta": 0.1}, KITTI, np.random.default_rng(0))


def test_npz_cache_roundtrip(tmp_path):
    t = fog.soft_return_table(0.03, r0_step=0.2, quad_nodes=8, cache_dir=tmp_path)
    files = list(tmp_path.glob("fog_soft_table_*.npz"))
    assert len(files) == 1
    fog._table.cache_clear()
    loaded = fog.soft_return_table(0.03, r0_step=0.2, quad_nodes=8, cache_dir=tmp_path)
    assert loaded is not t
    for k in ("r0", "r_fog", "i_fog", "r_lo", "r_hi"):
        assert np.array_equal(getattr(loaded, k), getattr(t, k))
    assert loaded.peak_range == t.peak_range
    files[0].write_bytes(b"garbage")  # a corrupt entry is rebuilt, not trusted
    fog._table.cache_clear()
    rebuilt = fog.soft_return_table(0.03, r0_step=0.2, quad_nodes=8, cache_dir=tmp_path)
    assert np.array_equal(rebuilt.i_fog, t.i_fog)
    assert np.load(files[0])["i_fog"].shape == t.i_fog.shape


def test_accuracy_time_curve_smoke(kitti_scan):
    scan = Scan(kitti_scan.points[::20])
    rows = fog.accuracy_time_curve(scan, KITTI, "heavy", seeds=[0])
    assert len(rows) == sum(len(v) for v in fog.FIDELITY_LEVELS.values())
    for row in rows:
        assert row["apply_s"] > 0 and row["table_s"] > 0
        assert all(np.isfinite(row[k]) and row[k] >= 0 for k in row if k.startswith("err_"))
    best = [r for r in rows if r["knob"] == "quad_nodes" and r["value"] == 64]
    coarse = [r for r in rows if r["knob"] == "quad_nodes" and r["value"] == 2]
    assert best[0]["err_fog_fraction"] <= coarse[0]["err_fog_fraction"]
