"""Ring recovery and beam reduction: on real KITTI and nuScenes scans (their firing order and
ring channel are the truth), order independence on a synthetic sweep."""

import numpy as np
import pytest

from omnilidar.data.rings import beam_reduce, recover_rings
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import PRESETS

from real_samples import NUSCENES_SWEEP, needs_real, real_file
HDL64 = PRESETS["kitti_hdl64e"]


def _kitti(name: str = "000000"):
    return np.fromfile(real_file(f"kitti_object/velodyne/{name}.bin"), np.float32).reshape(-1, 4)


def _firing_order_rings(points):
    """Reference rings of a raw KITTI scan: each laser's points are one revolution
    in firing order, starting at azimuth 0, so the unwrapped azimuth counts turns."""
    turns = np.floor(np.unwrap(np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)) / (2 * np.pi))
    return (turns - turns.min()).astype(np.int64)


@pytest.fixture(scope="module")
def kitti_rings():
    pts = _kitti()
    return pts, _firing_order_rings(pts), recover_rings(pts, HDL64)


def test_kitti_matches_firing_order(kitti_rings):
    pts, ref, rings = kitti_rings
    assert ref.max() == 63
    assert rings.dtype == np.int16 and rings.shape == (len(pts),)
    assert (rings == ref).mean() > 0.999
    # the plain nominal table is far off on this unit (offsets > one beam pitch)
    assert (recover_rings(pts, HDL64, calibrate=False) == ref).mean() < 0.5


def test_order_independent(synthetic_sweep):
    pts = synthetic_sweep.points
    rings = recover_rings(pts, HDL64)
    perm = np.random.default_rng(0).permutation(len(pts))
    assert np.array_equal(recover_rings(pts[perm], HDL64), rings[perm])


def test_synthetic_beams_exact():
    # ideal sensor at nominal angles with a per-laser height offset
    rng = np.random.default_rng(1)
    n_beams = HDL64.num_beams
    beam = rng.integers(0, n_beams, 40000)
    theta = HDL64.elevations_rad[beam]
    rho = rng.uniform(3.0, 60.0, len(beam))
    az = rng.uniform(-np.pi, np.pi, len(beam))
    z = rho * np.tan(theta) + 0.15
    pts = np.stack([rho * np.cos(az), rho * np.sin(az), z, np.zeros_like(z)], 1).astype(np.float32)
    assert (recover_rings(pts, HDL64) == beam).mean() > 0.999


def test_non_finite_get_minus_one_and_small_scans_fall_back():
    from omnilidar.data.rings import RingRecoveryWarning

    pts = np.array([[np.nan, 0, 0, 0], [10, 0, 0.0, 0], [0, 0, 0, 0]], np.float32)
    with pytest.warns(RingRecoveryWarning):  # never silently
        rings = recover_rings(pts, HDL64)
    assert rings[0] == -1
    assert 0 <= rings[1] <= 63 and 0 <= rings[2] <= 63
    # 10 m ahead at z = 10 * tan(-24.33 deg): the bottom beam
    low = np.array([[10, 0, 10 * np.tan(np.deg2rad(-24.33)), 0]], np.float32)
    assert recover_rings(low, HDL64)[0] == 63
    assert recover_rings(np.zeros((0, 4), np.float32), HDL64).shape == (0,)


@needs_real(NUSCENES_SWEEP)
def test_nuscenes_rings_agree_where_geometry_is_defined():
    raw = np.fromfile(real_file(NUSCENES_SWEEP), np.float32).reshape(-1, 5)
    sensor = PRESETS["nuscenes_hdl32e"]
    truth = 31 - raw[:, 4].astype(np.int64)  # nuScenes numbers rings bottom-up
    rings = recover_rings(raw[:, :4], sensor)
    r = np.linalg.norm(raw[:, :3], axis=1)
    usable = (r > sensor.min_range) & (r < sensor.max_range)
    assert (rings == truth)[usable].mean() > 0.85


def test_beam_reduce_uses_given_rings_and_keeps_order():
    pts = np.arange(40, dtype=np.float32).reshape(10, 4)
    scan = Scan(points=pts, semantic=np.arange(10), ring=np.array([0, 1, 2, 3, 4, 5, 6, 7, 0, 1]))
    out = beam_reduce(scan, HDL64)
    assert out.ring.tolist() == [0, 2, 4, 6, 0]
    assert out.semantic.tolist() == [0, 2, 4, 6, 8]
    np.testing.assert_array_equal(out.points, pts[[0, 2, 4, 6, 8]])
    assert len(beam_reduce(scan, HDL64, keep_every=4)) == 3
    assert len(scan) == 10  # input untouched


def test_beam_reduce_recovers_rings_on_real_scan(kitti_rings):
    pts, ref, _ = kitti_rings
    scan = Scan(points=pts, semantic=np.arange(len(pts)) % 7)
    out = beam_reduce(scan, HDL64)
    assert out.ring is not None and np.all(out.ring % 2 == 0)
    assert 0.45 < len(out) / len(scan) < 0.55
    kept = np.flatnonzero(ref % 2 == 0)
    assert len(out) == len(kept) and np.array_equal(out.semantic, scan.semantic[kept])


def test_a_units_calibration_recovers_rings_of_cropped_and_thinned_scans(kitti_rings):
    """Calibrated once on a full sweep, the unit's beam lines label crops that miss beams
    (front crop: the car body hides the lowest beams) and Beam-32-thinned sweeps."""
    from omnilidar.data.rings import calibrate_rings

    pts, ref, _ = kitti_rings
    calibration = calibrate_rings(pts, HDL64)
    assert calibration is not None and calibration.intercept.shape == (64,)
    other = _kitti("000001")
    other_ref = _firing_order_rings(other)
    az = np.degrees(np.arctan2(other[:, 1], other[:, 0]))
    for keep in (np.abs(az) < 45, other_ref % 2 == 0, az > 0):
        rings = recover_rings(other[keep], HDL64, calibration=calibration)
        assert (rings == other_ref[keep]).mean() > 0.99
    # Without the unit's calibration, a front crop falls back to the nominal table.
    front = np.abs(az) < 45
    assert (recover_rings(other[front], HDL64) == other_ref[front]).mean() < 0.5


def test_a_partial_view_is_calibrated_with_a_warning_and_recorded(synthetic_sweep):
    import warnings

    from omnilidar.data.rings import RingRecoveryWarning, ring_recovery

    sensor = PRESETS["kitti_hdl64e"]
    pts = synthetic_sweep.points[np.random.default_rng(0).permutation(len(synthetic_sweep))]  # not in firing order
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        full, method = ring_recovery(pts, sensor)
    assert method == "scan_calibration"
    azimuth = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    crop = pts[np.abs(azimuth) <= 45.0]  # a camera-view crop
    with pytest.warns(RingRecoveryWarning, match="partial view"):
        rings, method = ring_recovery(crop, sensor)
    assert method == "scan_calibration_partial_view" and len(rings) == len(crop)
