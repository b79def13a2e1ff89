"""Snow effect: formulas, occlusion, waveform peak, strongest-return outcomes, and the
effect contract (identity, untouched beams bit for bit, determinism, stability).

The contract runs on a synthetic full sweep; the clutter and loss shares stated for
real KITTI geometry are checked on the real scan."""

from __future__ import annotations


import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from omnilidar.domains.effects import snow
from omnilidar.domains.effects.base import WEATHER_RETURN_LABEL
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Boxes, Scan
from omnilidar.lidar.sensors import PRESETS

from real_samples import real_file
KITTI = PRESETS["kitti_hdl64e"]
NUSC = PRESETS["nuscenes_hdl32e"]
L_PULSE = snow.SPEED_OF_LIGHT * snow.PULSE_HALF_POWER_WIDTH


def _labelled(pts: np.ndarray) -> Scan:
    """A sweep's points with random labels and instances, rings and one box."""
    n = len(pts)
    rng = np.random.default_rng(7)
    boxes = Boxes(np.array([[10, 2, -1, 4, 2, 1.5, 0.3]], np.float32), np.array(["Car"]), np.array([5]))
    return Scan(pts, rng.integers(9, 80, n).astype(np.uint16), rng.integers(0, 20, n).astype(np.uint16),
                np.arange(n) % 64, boxes, 1.0)


def _all_runs(scan: Scan) -> dict:
    return {(sev, s): snow.apply(scan, snow.SEVERITIES[sev], KITTI, np.random.default_rng(s), return_info=True)
            for sev in snow.SEVERITIES for s in (0, 1)}


@pytest.fixture(scope="module")
def kitti(synthetic_sweep):
    """A full synthetic HDL-64E sweep."""
    return _labelled(synthetic_sweep.points)


@pytest.fixture(scope="module")
def runs(kitti):
    """(out, info) for every severity and two seeds, computed once."""
    return _all_runs(kitti)


# ------------------------------------------------------------------ formulas


def test_snowfall_formulas_hand_computed():
    # light: 487 * 0.1 * 0.003 * 2.0 = 0.2922; (0.5 / 0.2922)^1.5 = 2.2384 mm/h
    assert snow.equivalent_rain_rate(0.5, 2.0) == pytest.approx((0.5 / 0.2922) ** 1.5, rel=1e-12)
    assert snow.equivalent_rain_rate(2.5, 1.6) == pytest.approx(34.9748, rel=1e-4)
    assert snow.snow_volume_fraction(0.5, 2.0) == pytest.approx(0.5 / (3.6e6 * 0.1 * 2.0))
    assert snow.gunn_marshall_rate(1.0) == pytest.approx(2550.0)  # 25.5 per cm
    assert snow.gunn_marshall_rate(8.0) == pytest.approx(2550.0 * 8.0 ** -0.48)
    # truncated exponential moments: untruncated limit is k! / rate^k
    assert snow.truncated_exponential_moment(5000.0, 3) == pytest.approx(6 / 5000.0 ** 3, rel=1e-9)
    # truncation lowers the mean: rate 100/m (mean 1 cm) capped at 2 cm
    x = 100.0 * 0.02
    mean = (1 - (1 + x) * np.exp(-x)) / (100.0 * (1 - np.exp(-x)))
    assert snow.truncated_exponential_moment(100.0, 1) == pytest.approx(mean, rel=1e-9)


def test_overlap_fraction_geometry():
    f = snow.overlap_fraction
    assert f(1.0, 0.1, 0.0) == pytest.approx(0.01)  # small flake inside: (a / b)^2
    assert f(1.0, 0.1, 0.85) == pytest.approx(0.01)  # still inside
    assert f(1.0, 2.0, 0.5) == 1.0  # flake covers the beam
    assert f(1.0, 0.1, 1.2) == 0.0  # disjoint
    # equal circles one radius apart: lens = R^2 (2 pi / 3 - sqrt(3) / 2)
    assert f(1.0, 1.0, 1.0) == pytest.approx((2 * np.pi / 3 - np.sqrt(3) / 2) / np.pi, rel=1e-12)
    # a flake centred on the beam edge covers about half of its own area
    assert f(10.0, 0.1, 10.0) == pytest.approx(0.5 * 0.01 / 100, rel=2e-2)
    out = f(np.zeros(3), np.array([0.0, 0.1, 0.1]), np.array([0.0, 0.0, 1.0]))
    assert np.isfinite(out).all() and (out >= 0).all() and (out <= 1).all()


def test_visible_fractions_front_to_back():
    beam = np.array([0, 0, 1, 1, 1, 2])
    f = np.array([0.5, 0.5, 0.2, 1.0, 0.3, 0.0])
    v, vt = snow.visible_fractions(beam, f, 4)
    assert v == pytest.approx([0.5, 0.25, 0.2, 0.8, 0.0, 0.0])
    assert vt == pytest.approx([0.25, 0.0, 1.0, 1.0])


def _dense_peak(pos, amp, L, step=1e-4):
    x = np.arange(0.0, pos.max() + L + step, step)
    w = sum(a * np.where((x >= p) & (x <= p + L), np.sin(np.pi * (x - p) / L) ** 2, 0.0) for p, a in zip(pos, amp))
    return w.max(), x[np.argmax(w)]


def test_waveform_peak_single_pulse_and_closed_form():
    peak, x = snow.waveform_peaks(np.array([0]), np.array([7.0]), np.array([0.4]), 1, L_PULSE)
    assert peak[0] == pytest.approx(0.4) and x[0] == pytest.approx(7.0 + L_PULSE / 2)
    rng = np.random.default_rng(3)
    groups, pos, amp, want = [], [], [], []
    for g in range(12):
        k = rng.integers(1, 5)
        p = np.sort(rng.uniform(1.0, 15.0, k))
        a = rng.uniform(0.01, 1.0, k)
        groups += [g] * k
        pos += list(p)
        amp += list(a)
        want.append(_dense_peak(p, a, L_PULSE))
    peak, x = snow.waveform_peaks(np.array(groups), np.array(pos), np.array(amp), 12, L_PULSE)
    for g, (wv, wx) in enumerate(want):
        assert peak[g] == pytest.approx(wv, abs=1e-7)
        assert peak[g] >= wv - 1e-12  # exact max is never below a sampled value
    # binned: the max over the 0.1 m grid equals brute force on that grid
    pb, xb = snow.waveform_peaks(np.array(groups), np.array(pos), np.array(amp), 12, L_PULSE, range_bin=0.1)
    for g in range(12):
        sel = np.array(groups) == g
        gp, ga = np.array(pos)[sel], np.array(amp)[sel]
        grid = np.arange(0, 40, 0.1)
        w = sum(a * np.where((grid >= p) & (grid <= p + L_PULSE), np.sin(np.pi * (grid - p) / L_PULSE) ** 2, 0.0)
                for p, a in zip(gp, ga))
        assert pb[g] == pytest.approx(w.max(), abs=1e-9)
        assert pb[g] <= peak[g] + 1e-12


# ------------------------------------------------------------------ strongest return, hand-built beams


def _one_beam(monkeypatch, flakes, d=20.0, rho=0.6):
    """Scan with one beam at range d along x; flakes (r, f) forced into it."""
    r = np.array([fl[0] for fl in flakes], float)
    f = np.array([fl[1] for fl in flakes], float)
    monkeypatch.setattr(snow, "sample_flakes", lambda *a, **k: (np.zeros(len(r), np.int64), r, f))
    scan = Scan(np.array([[d, 0, 0, rho], [5, 5, 0, 0.3]], np.float32), np.array([40, 50]), np.array([3, 4]))
    return snow.apply(scan, snow.SEVERITIES["heavy"], KITTI, np.random.default_rng(0), return_info=True)


def test_partial_occlusion_dims_target(monkeypatch):
    out, info = _one_beam(monkeypatch, [(3.0, 0.2)])
    # target 0.6 * 0.8 = 0.48 beats the flake 0.9 * 0.2 = 0.18; pulses 17 m apart
    assert out.points[0, 3] == pytest.approx(0.48, rel=1e-6)
    assert np.array_equal(out.points[0, :3], [20, 0, 0])
    assert out.semantic[0] == 40 and info["changed"][0] and not info["weather"][0]
    assert np.array_equal(out.points[1], np.float32([5, 5, 0, 0.3])) and not info["changed"][1]


def test_strong_flake_becomes_weather_return(monkeypatch):
    out, info = _one_beam(monkeypatch, [(2.0, 0.5)])
    # flake 0.9 * 0.5 = 0.45 beats the target 0.6 * 0.5 = 0.3: snow point at 2 m
    assert info["weather"][0] and info["changed"][0] and not info["lost"].any()
    assert out.points[0, :3] == pytest.approx([2.0, 0, 0], abs=1e-6)
    assert out.points[0, 3] == pytest.approx(0.45, rel=1e-6)
    assert out.semantic[0] == WEATHER_RETURN_LABEL and out.instance[0] == 0


def test_overlapping_pulses_add(monkeypatch):
    # flake 2 m before the target: pulses overlap, the sum exceeds either one
    out, info = _one_beam(monkeypatch, [(18.0, 0.1)], d=20.0, rho=0.5)
    a_t, a_f = 0.45, 0.09
    want, _ = _dense_peak(np.array([18.0, 20.0]), np.array([a_f, a_t]), L_PULSE)
    assert out.points[0, 3] == pytest.approx(want, rel=1e-5) and want > a_t
    assert not info["weather"][0]


def test_full_occlusion_by_gated_flake_loses_point(monkeypatch):
    # a flake inside the 1.45 m minimum range blocks the whole beam: no return
    out, info = _one_beam(monkeypatch, [(1.2, 1.0)])
    assert info["lost"].tolist() == [True, False]
    assert len(out) == 1 and np.array_equal(out.points[0], np.float32([5, 5, 0, 0.3])) and out.semantic[0] == 50


def test_zero_remission_target_is_not_special(monkeypatch):
    out, info = _one_beam(monkeypatch, [(4.0, 0.05)], rho=0.0)
    # competes as reflectance 0.1 (0.095 > 0.045): stays a target, intensity stays 0
    assert not info["weather"][0] and not info["lost"][0]
    assert out.points[0, 3] == 0.0 and not info["changed"][0]


# ------------------------------------------------------------------ contract on a full sweep


def test_zero_severity_is_identity(kitti):
    assert snow.apply(kitti, {"snowfall_rate": 0.0, "terminal_velocity": 1.6}, KITTI, np.random.default_rng(0)) is kitti
    out, info = snow.apply(kitti, {"snowfall_rate": 0.0}, KITTI, np.random.default_rng(0), return_info=True)
    assert out is kitti and not info["lost"].any() and not info["changed"].any() and len(info["weather"]) == len(kitti)


def test_untouched_beams_bit_for_bit(kitti, runs):
    d = np.linalg.norm(kitti.points[:, :3].astype(np.float64), axis=1)
    theta = KITTI.beam_divergence_mrad * 1e-3
    for sev in snow.SEVERITIES:
        out, info = runs[(sev, 0)]
        beam, _, _ = snow.sample_flakes(d, snow.SEVERITIES[sev], theta, np.random.default_rng(0),
                                        snow.DEFAULT_FIDELITY["min_fraction"])
        untouched = np.ones(len(kitti), bool)
        untouched[beam] = False
        assert untouched.mean() > 0.5
        assert not info["lost"][untouched].any() and not info["changed"][untouched].any()
        kept_untouched = untouched[~info["lost"]]
        src = np.flatnonzero(~info["lost"])[kept_untouched]
        assert np.array_equal(out.points[kept_untouched].view(np.uint32), kitti.points[src].view(np.uint32))
        assert np.array_equal(out.semantic[kept_untouched], kitti.semantic[src])
        assert np.array_equal(out.instance[kept_untouched], kitti.instance[src])
        # everything that changed or was lost is in a touched beam
        assert not (info["lost"] | info["changed"])[untouched].any()


def _check_monotone(scan: Scan, runs: dict) -> dict:
    """Checks every share grows (and intensity drops) with severity; returns the heavy shares."""
    def stat(sev):
        rows = [snow.summary(scan, *runs[(sev, s)]) for s in (0, 1)]
        return {k: np.mean([r[k] for r in rows]) for k in ("weather", "lost", "changed", "intensity_shift_mean")}

    light, moderate, heavy = (stat(s) for s in ("light", "moderate", "heavy"))
    for k in ("weather", "lost", "changed"):
        assert light[k] < moderate[k] < heavy[k], k
    assert light["intensity_shift_mean"] > moderate["intensity_shift_mean"] > heavy["intensity_shift_mean"]
    assert heavy["intensity_shift_mean"] < 0
    return heavy


def test_monotone_in_severity(kitti, runs):
    _check_monotone(kitti, runs)


def test_heavy_snow_on_real_kitti_is_clutter_not_a_wipe_out():
    scan = _labelled(np.fromfile(real_file("kitti_object/velodyne/000001.bin"), np.float32).reshape(-1, 4))
    heavy = _check_monotone(scan, _all_runs(scan))
    assert heavy["weather"] < 0.05 and heavy["lost"] < 0.01  # snow clutter, not a wipe-out


def test_outputs_physical_and_labels_carried(kitti, runs):
    d_in = np.linalg.norm(kitti.points[:, :3].astype(np.float64), axis=1)
    for (sev, s), (out, info) in runs.items():
        keep = ~info["lost"]
        assert len(out) == keep.sum() == len(info["weather"])
        assert np.isfinite(out.points).all()
        d_out = np.linalg.norm(out.points[:, :3].astype(np.float64), axis=1)
        assert (d_out <= d_in[keep] + 1e-9).all()
        w = info["weather"]
        assert (d_out[w] >= KITTI.min_range - 1e-6).all() and (d_out[w] > 0).all()
        assert (out.intensity >= 0).all() and (out.intensity <= 1).all()
        assert (out.semantic[w] == WEATHER_RETURN_LABEL).all() and (out.instance[w] == 0).all()
        assert np.array_equal(out.semantic[~w], kitti.semantic[keep][~w])
        assert np.array_equal(out.instance[~w], kitti.instance[keep][~w])
        assert np.array_equal(out.ring, kitti.ring[keep]) and out.boxes is kitti.boxes
        # snow points lie on their beam: same direction, shorter range
        u_in = kitti.points[keep][w, :3] / d_in[keep][w, None]
        assert np.allclose(out.points[w, :3] / d_out[w, None], u_in, atol=1e-5)
        # kept targets are never moved
        tgt = ~w
        assert np.array_equal(out.points[tgt, :3], kitti.points[keep][tgt, :3])
        assert info["changed"][keep][w].all()


def test_deterministic_and_seed_dependent(kitti, runs):
    out, info = snow.apply(kitti, snow.SEVERITIES["moderate"], KITTI, np.random.default_rng(0), return_info=True)
    ref, ref_info = runs[("moderate", 0)]
    assert np.array_equal(out.points, ref.points) and np.array_equal(info["lost"], ref_info["lost"])
    other, _ = runs[("moderate", 1)]
    assert len(other) != len(ref) or not np.array_equal(other.points, ref.points)


def test_nuscenes_scale_and_other_scans(synthetic_nuscenes_sweep):
    sweep = synthetic_nuscenes_sweep
    scan = Scan(sweep.points, ring=sweep.ring, intensity_scale=255.0)
    out, info = snow.apply(scan, snow.SEVERITIES["heavy"], NUSC, np.random.default_rng(2), return_info=True)
    assert (out.intensity >= 0).all() and (out.intensity <= 255).all()
    assert info["weather"].any() and info["changed"].any()
    # weather intensities are on the 0..255 scale (0.9 * covered fraction)
    assert out.intensity[info["weather"]].max() > 1.0


def test_fidelity_knobs(kitti):
    sub = kitti.select(np.arange(0, len(kitti), 4))
    params = snow.SEVERITIES["heavy"]
    exact, ie = snow.apply(sub, params, KITTI, np.random.default_rng(5), return_info=True)
    binned, ib = snow.apply(sub, params, KITTI, np.random.default_rng(5), fidelity={"range_bin": 0.1},
                            return_info=True)
    # same flakes, same outcomes up to the bin grid's peak error (<= 0.3 % of a pulse peak)
    assert np.array_equal(ie["lost"], ib["lost"])
    assert np.allclose(exact.intensity, binned.intensity, atol=5e-3)
    capped, ic = snow.apply(sub, params, KITTI, np.random.default_rng(5), fidelity={"max_flakes": 1},
                            return_info=True)
    assert ic["changed"].sum() <= ie["changed"].sum() + ie["lost"].sum()
    fine = snow.apply(sub, params, KITTI, np.random.default_rng(5), fidelity={"min_fraction": 1e-3})
    assert np.isfinite(fine.points).all()
    with pytest.raises(InputError):
        snow.apply(sub, params, KITTI, np.random.default_rng(5), fidelity={"samples": 3})
    with pytest.raises(InputError):
        snow.apply(sub, params, KITTI, np.random.default_rng(5), fidelity={"min_fraction": 0.0})


def test_accuracy_time_curve_rows(kitti):
    sub = kitti.select(np.arange(0, len(kitti), 16))
    rows = snow.accuracy_time_curve(sub, KITTI, "heavy", seeds=[0])
    assert len(rows) == sum(len(v) for v in snow.FIDELITY_LEVELS.values())
    for row in rows:
        assert row["time_s"] > 0 and all(np.isfinite(row[k]) for k in row if k.startswith("err_"))
    best = [r for r in rows if r["knob"] == "range_bin" and r["value"] == 0.0][0]
    assert best["err_lost"] == 0.0 and best["err_weather"] == 0.0


# ------------------------------------------------------------------ bad input and edge cases


def test_bad_input_raises():
    scan = Scan(np.array([[1, 2, 3, 0.5], [np.nan, 0, 0, 0.1]], np.float32))
    with pytest.raises(InputError, match="NaN"):
        snow.apply(scan, snow.SEVERITIES["light"], KITTI, np.random.default_rng(0))
    good = Scan(np.array([[10, 0, 0, 0.5]], np.float32))
    for params in ({"snowfall_rate": -1.0, "terminal_velocity": 1.0}, {"snowfall_rate": 1.0, "terminal_velocity": 0},
                   {"snowfall_rate": 1.0, "wind": 3}, {"snowfall_rate": "lots"}, {"snowfall_rate": float("inf")}):
        with pytest.raises(InputError):
            snow.apply(good, params, KITTI, np.random.default_rng(0))
    with pytest.raises(InputError, match="severity"):
        snow.draw_params("blizzard", np.random.default_rng(0))
    assert snow.draw_params("heavy", np.random.default_rng(0)) == {"snowfall_rate": 2.5, "terminal_velocity": 1.6}


def test_degenerate_scans():
    rng = np.random.default_rng(0)
    empty = Scan(np.zeros((0, 4), np.float32))
    out, info = snow.apply(empty, snow.SEVERITIES["heavy"], KITTI, rng, return_info=True)
    assert len(out) == 0 and info["lost"].shape == (0,) and info["weather"].shape == (0,)
    tiny = Scan(np.array([[0, 0, 0, 0], [1e-7, 0, 0, 1.0], [1e-3, 1e-3, 0, 0]], np.float32), np.array([1, 2, 3]))
    out = snow.apply(tiny, {"snowfall_rate": 50.0, "terminal_velocity": 0.2}, KITTI, rng)
    assert np.array_equal(out.points, tiny.points)  # no room for a flake in front of r ~ 0
    one = Scan(np.array([[60.0, 0, 0, 0.0]], np.float32))
    for s in range(20):
        out = snow.apply(one, {"snowfall_rate": 20.0, "terminal_velocity": 0.2}, KITTI, np.random.default_rng(s))
        assert np.isfinite(out.points).all() and len(out) <= 1


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(1, 300),
    seed=st.integers(0, 2**31 - 1),
    rate=st.floats(0.01, 30.0),
    velocity=st.floats(0.1, 3.0),
    nusc=st.booleans(),
    min_fraction=st.sampled_from([1e-1, 1e-2, 1e-3]),
)
def test_property_no_nan_ranges_and_intensities(n, seed, rate, velocity, nusc, min_fraction):
    rng = np.random.default_rng(seed)
    sensor, scale = (NUSC, 255.0) if nusc else (KITTI, 1.0)
    xyz = rng.normal(size=(n, 3)) * rng.choice([1e-6, 0.5, 3.0, 30.0, 120.0], size=(n, 1))
    inten = rng.choice([0.0, 0.01, 0.5, 1.0], size=n) * scale
    scan = Scan(np.column_stack([xyz, inten]).astype(np.float32), rng.integers(0, 260, n), rng.integers(0, 9, n),
                intensity_scale=scale)
    out, info = snow.apply(scan, {"snowfall_rate": rate, "terminal_velocity": velocity}, sensor, rng,
                           fidelity={"min_fraction": min_fraction}, return_info=True)
    assert np.isfinite(out.points).all()
    keep = ~info["lost"]
    d_in = np.linalg.norm(scan.points[keep, :3].astype(np.float64), axis=1)
    d_out = np.linalg.norm(out.points[:, :3].astype(np.float64), axis=1)
    assert (d_out <= d_in + 1e-9).all()
    assert (d_out[info["weather"]] > 0).all()
    assert (out.intensity >= 0).all() and (out.intensity <= scale).all()
    same = keep & ~info["changed"]
    assert np.array_equal(out.points[same[keep]], scan.points[same])
