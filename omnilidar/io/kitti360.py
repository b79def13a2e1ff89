"""KITTI-360 raw scans: ``data_3d_raw/2013_05_28_drive_{seq:04d}_sync/velodyne_points/data/{frame:010d}.bin``.

The files use the KITTI format (float32 x, y, z, remission 0..1), so reading
and writing follow :mod:`omnilidar.io.semantickitti` (same checks, same
empty-scan policy). ``SPLITS`` is the R2DM generation split.
"""

from __future__ import annotations

import operator
from pathlib import Path

from omnilidar.errors import InputError
from omnilidar.io import pointfile, semantickitti
from omnilidar.lidar.scan import Scan

SPLITS: dict[str, list[int]] = {"train": [3, 4, 5, 6, 7, 9, 10], "test": [0, 2]}
SEQUENCES: tuple[int, ...] = (0, 2, 3, 4, 5, 6, 7, 9, 10)  # the 9 published drives


def _check_index(name: str, value: int) -> int:
    try:
        index = operator.index(value)  # ints and numpy integers, not floats or strings
    except TypeError:
        index = -1
    if isinstance(value, bool) or index < 0:
        raise InputError(None, f"KITTI-360 {name} must be a non-negative int, got {value!r}")
    return index


def sequence_dir(root: str | Path, sequence: int) -> Path:
    """The folder holding one drive's scans (it may not exist)."""
    seq = _check_index("sequence", sequence)
    return Path(root) / "data_3d_raw" / f"2013_05_28_drive_{seq:04d}_sync" / "velodyne_points" / "data"


def scan_path(root: str | Path, sequence: int, frame: int) -> Path:
    """Path of one raw scan (it may not exist)."""
    return sequence_dir(root, sequence) / f"{_check_index('frame', frame):010d}.bin"


def read_scan(path: str | Path) -> Scan:
    """Read one KITTI-360 scan (intensity_scale 1.0); empty scans are an error."""
    return semantickitti.read_scan(path)


def write_scan(scan: Scan, path: str | Path) -> None:
    """Write a scan as a KITTI-360 ``.bin`` (remission rescaled to 0..1), atomically."""
    semantickitti.write_scan(scan, path)


def sequence_paths(root: str | Path, sequence: int) -> list[Path]:
    """All scans of one drive, sorted by frame number."""
    root = pointfile.require_dir(root, "KITTI-360 root")
    folder = pointfile.require_dir(sequence_dir(root, sequence), "KITTI-360 sequence folder")
    scans = sorted(folder.glob("*.bin"))
    if not scans:
        raise InputError(folder, "holds no .bin scans")
    return scans
