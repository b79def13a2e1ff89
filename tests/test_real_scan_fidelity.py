"""Domain fidelity on real KITTI and SemanticKITTI scans: lasers recovered from the
firing order (Beam-32 keeps exactly the chosen lasers), no silent ring fallback,
wet ground continuous in the water height, and one point check at the builder's
entry for every effect."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from real_samples import KITTI_SCANS, REAL, SEMANTICKITTI_SCAN, needs_real

from omnilidar.data.rings import RingRecoveryWarning, calibrate_rings, firing_order_rings, ring_recovery
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import PRESETS
from omnilidar.domains import builder as B
from omnilidar.domains import ground as G
from omnilidar.domains.effects import wet_ground as W
from omnilidar.domains.spec import EffectSpec, SceneSpec
from omnilidar.errors import InputError

pytestmark = needs_real(SEMANTICKITTI_SCAN, KITTI_SCANS)
SEMKITTI = REAL / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin"
KITTI = [REAL / "kitti_object" / "velodyne" / f"00000{i}.bin" for i in (0, 1)]
HDL64 = PRESETS["kitti_hdl64e"]


def _read(path: Path) -> np.ndarray:
    return np.fromfile(path, np.float32).reshape(-1, 4)


def _turns(points: np.ndarray) -> np.ndarray:
    """Reference lasers of a scan stored in firing order: unwrapped-azimuth revolutions."""
    turns = np.floor(np.unwrap(np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)) / (2 * np.pi))
    return (turns - turns.min()).astype(np.int64)


def _scene(name: str, severity: str) -> SceneSpec:
    return SceneSpec((EffectSpec(name, (severity,)),))


@pytest.fixture(scope="module")
def semkitti():
    return _read(SEMKITTI)


# ------------------------------------------------------------------ rings


def test_semantickitti_lasers_come_from_the_firing_order(semkitti):
    rings, method = ring_recovery(semkitti, HDL64)
    assert method == "firing_order"
    assert np.array_equal(rings, _turns(semkitti)) and rings.max() == 63
    # A unit calibration now exists (fitted to the firing-order lasers).
    assert calibrate_rings(semkitti, HDL64) is not None


@pytest.mark.parametrize("path", KITTI, ids=["kitti0", "kitti1"])
def test_firing_order_agrees_with_the_order_free_calibration_on_kitti(path):
    """Two independent methods: file order vs the per-scan line calibration of a shuffled copy."""
    pts = _read(path)
    rings, method = ring_recovery(pts, HDL64)
    perm = np.random.default_rng(0).permutation(len(pts))
    shuffled, shuffled_method = ring_recovery(pts[perm], HDL64)
    assert (method, shuffled_method) == ("firing_order", "scan_calibration")
    assert (shuffled == rings[perm]).mean() > 0.9999


def test_firing_order_is_refused_when_the_order_is_not_firing_order(semkitti):
    ref = _turns(semkitti)
    az = np.degrees(np.arctan2(semkitti[:, 1], semkitti[:, 0]))
    shuffled = semkitti[np.random.default_rng(1).permutation(len(semkitti))]
    reversed_lasers = np.concatenate([semkitti[ref == k] for k in range(63, -1, -1)])
    for variant in (shuffled, semkitti[np.abs(az) < 45], semkitti[ref % 2 == 0], reversed_lasers):
        assert firing_order_rings(variant, HDL64) is None


def test_no_silent_fallback_to_the_nominal_table(semkitti):
    """Shuffled SemanticKITTI (ego-motion compensated, so the line calibration fails
    too) falls back to the nominal table: it warns, and the builder records it."""
    scan = Scan(semkitti[np.random.default_rng(2).permutation(len(semkitti))])
    with pytest.warns(RingRecoveryWarning, match="nominal beam table"):
        _, record = B.build_scan(scan, _scene("beam_reduction", "half"), HDL64, np.random.default_rng(0), "shuffled.bin")
    assert record["effects"][0]["outcome"]["ring_method"] == "nominal"
    assert len(record["warnings"]) == 1 and record["warnings"][0].startswith("shuffled.bin: ")


def test_beam32_from_semantickitti_keeps_exactly_the_even_lasers(semkitti):
    scan = Scan(semkitti, semantic=np.arange(len(semkitti)) % 20)
    out, record = B.build_scan(scan, _scene("beam_reduction", "half"), HDL64, np.random.default_rng(0), SEMKITTI)
    assert record["effects"][0]["outcome"]["ring_method"] == "firing_order" and "warnings" not in record
    even = np.flatnonzero(_turns(semkitti) % 2 == 0)
    assert np.array_equal(out.points, semkitti[even]) and np.array_equal(out.semantic, scan.semantic[even])
    # A ring-indexed range image of the result has exactly 32 non-empty rows.
    assert np.count_nonzero(np.bincount(out.ring, minlength=64)) == 32


# ------------------------------------------------------------------ wet ground


@pytest.mark.parametrize("path", [KITTI[0], SEMKITTI], ids=["kitti0", "semkitti"])
def test_wet_ground_loss_goes_continuously_to_none_with_the_water(path):
    scan = Scan(_read(path))
    ground = G.estimate_ground(scan, HDL64)
    lost = []
    for water in (0.0, 1e-6, 1e-3, 0.05, 0.2, 1.0):
        _, info = W.apply(scan, {"water_height_mm": water, "noise_floor": 0.3}, HDL64, np.random.default_rng(0),
                          ground=ground, return_info=True)
        lost.append(int(info["lost"].sum()))
    assert lost[0] == 0 and lost[1] <= 1  # was 179-249 at 1e-6 mm
    assert all(a <= b for a, b in zip(lost, lost[1:])), lost
    assert lost[4] > 0 and lost[5] > 200  # light (0.2 mm) and 1 mm of water still lose ground


def test_zero_water_is_the_identity_without_ground_estimation(semkitti, monkeypatch):
    monkeypatch.setattr(G, "estimate_ground", lambda *a, **k: pytest.fail("zero water estimated ground"))
    scan = Scan(semkitti)
    record = {"effects": [{"name": "wet_ground", "params": {"water_height_mm": 0.0, "noise_floor": 0.7},
                           "seed": 3, "fidelity": {}}]}
    assert B.rebuild_scan(scan, record, HDL64) is scan


# ------------------------------------------------------------------ entry check

EFFECTS = [("fog", "heavy"), ("snow", "light"), ("rain", "heavy"), ("wet_ground", "heavy"),
           ("beam_reduction", "half"), ("beam_missing", "light")]


@pytest.mark.parametrize("name,severity", EFFECTS)
@pytest.mark.parametrize("problem", ["nan_xyz", "nan_intensity", "0..255", "negative"])
def test_bad_points_raise_one_clear_error_naming_the_file(name, severity, problem, monkeypatch):
    monkeypatch.setattr(G, "estimate_ground", lambda *a, **k: pytest.fail("checked before any work"))
    pts = _read(KITTI[0])[::50].copy()
    if problem == "nan_xyz":
        pts[7, 0] = np.nan
    elif problem == "nan_intensity":
        pts[7, 3] = np.nan
    elif problem == "0..255":
        pts[:, 3] *= 255.0
    else:
        pts[7, 3] = -0.1
    source = "sequences/00/velodyne/000042.bin"
    match = "NaN or infinite" if problem.startswith("nan") else "outside the kitti_hdl64e scale 0..1"
    with pytest.raises(InputError, match=match) as err:
        B.build_scan(Scan(pts), _scene(name, severity), HDL64, np.random.default_rng(0), source)
    assert err.value.path == source and "\n" not in str(err.value)
