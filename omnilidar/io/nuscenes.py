"""nuScenes LiDAR sweeps (``*.pcd.bin``) and lidarseg labels (``*_lidarseg.bin``).

A sweep is float32 little-endian records x, y, z, intensity (0..255), ring
(0..31, HDL-32E). nuScenes numbers rings from the BOTTOM beam: on the real
sample ring 0 has median elevation -30.6 deg and ring 31 +10.6 deg (elevation
rises monotonically, 1.33 deg a ring). Our ``Scan.ring`` counts from the TOP
beam (row 0 of a range image), so reading maps ring -> 31 - ring and writing
maps it back.

A lidarseg file is one uint8 class index (0..31) per point of its sweep.
Empty sweeps are rejected by ``read_scan`` as for KITTI (see
:mod:`omnilidar.io.semantickitti`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io import pointfile
from omnilidar.lidar.scan import Scan

POINT_LAYOUT = "float32 x,y,z,intensity,ring"
NUM_RINGS = 32  # HDL-32E
INTENSITY_MAX = 255.0
NUM_LIDARSEG_CLASSES = 32  # nuScenes-lidarseg general classes 0..31


def read_points(path: str | Path) -> np.ndarray:
    """Read a ``.pcd.bin`` as (N, 5) float32 x, y, z, intensity, ring (raw values).

    Checks the size (whole 20-byte records) and that all values are finite.
    """
    points = pointfile.read_records(path, "<f4", 5, POINT_LAYOUT)
    pointfile.check_finite(path, points, "coordinates, intensity or ring")
    return points.astype(np.float32, copy=False)


def _ring_to_ours(path, nusc_ring: np.ndarray) -> np.ndarray:
    bad = (nusc_ring != np.round(nusc_ring)) | (nusc_ring < 0) | (nusc_ring > NUM_RINGS - 1)
    if bad.any():
        raise InputError(
            path, f"{int(bad.sum())} of {len(nusc_ring)} points have a ring that is not an integer 0..{NUM_RINGS - 1}"
        )
    return (NUM_RINGS - 1 - nusc_ring).astype(np.int16)


def read_scan(path: str | Path) -> Scan:
    """Read a sweep into a Scan: intensity 0..255 (``intensity_scale`` 255.0) and
    ring with 0 = top beam. Empty sweeps and out-of-range values are errors."""
    raw = read_points(path)
    if len(raw) == 0:
        raise InputError(path, "scan has 0 points (an empty sweep means a truncated or failed export)")
    pointfile.check_range(path, raw[:, 3], 0.0, INTENSITY_MAX, "intensity")
    ring = _ring_to_ours(path, raw[:, 4])
    return Scan(points=np.ascontiguousarray(raw[:, :4]), ring=ring, intensity_scale=INTENSITY_MAX)


def write_scan(scan: Scan, path: str | Path) -> None:
    """Write a Scan as a nuScenes ``.pcd.bin``, atomically.

    Intensity is rescaled to 0..255 from ``scan.intensity_scale``; the scan
    must carry rings (0 = top beam, 0..31), written in nuScenes' bottom-up order.
    """
    points = pointfile.as_float_matrix(path, scan.points, 4, "points")
    if len(points) == 0:
        raise InputError(path, "refusing to write a scan with 0 points")
    if scan.ring is None:
        raise InputError(path, "scan has no ring ids; nuScenes sweeps need a ring per point")
    ring = np.asarray(scan.ring)
    if ring.min() < 0 or ring.max() > NUM_RINGS - 1:
        raise InputError(path, f"ring ids {ring.min()}..{ring.max()} outside 0..{NUM_RINGS - 1}")
    if scan.intensity_scale != INTENSITY_MAX:
        points[:, 3] *= np.float32(INTENSITY_MAX / scan.intensity_scale)
    pointfile.check_range(path, points[:, 3], 0.0, INTENSITY_MAX, "intensity")
    out = np.column_stack([points, (NUM_RINGS - 1 - ring).astype(np.float32)])
    pointfile.write_records(path, out, "<f4")


def read_lidarseg(path: str | Path, num_points: int) -> np.ndarray:
    """Read a lidarseg ``.bin`` (uint8 per point); the count must equal ``num_points``."""
    labels = pointfile.read_records(path, "u1", 1, "uint8 class per point")[:, 0]
    if len(labels) != num_points:
        raise InputError(path, f"has {len(labels)} labels but its scan has {num_points} points")
    if labels.size and labels.max() >= NUM_LIDARSEG_CLASSES:
        raise InputError(path, f"class {labels.max()} outside nuScenes-lidarseg's 0..{NUM_LIDARSEG_CLASSES - 1}")
    return labels


def write_lidarseg(path: str | Path, labels: np.ndarray) -> None:
    """Write per-point lidarseg classes (0..31) as uint8, atomically."""
    labels = pointfile.as_uint_vector(path, labels, 8, "lidarseg labels")
    if labels.size and labels.max() >= NUM_LIDARSEG_CLASSES:
        raise InputError(path, f"class {labels.max()} outside nuScenes-lidarseg's 0..{NUM_LIDARSEG_CLASSES - 1}")
    pointfile.write_records(path, labels, "u1")
