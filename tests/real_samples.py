"""Where the real LiDAR samples are: one setting for every test and benchmark that reads them.

The samples stay outside the repository (their licences keep them there). Set
OMNILIDAR_REAL_DATA to their folder (relative paths are taken from the repository
root); the default is ../shared/data/real beside the repository. Only checks of
real sensor data read them (readers on the real formats, real ring order, effects
measured on real geometry, agreement with numbers measured on real scans); tests
that merely need some full sweep use the synthetic one (conftest.py). Without the
samples, or without one of the files a test names, that test skips with one reason
and every other test runs. Benchmarks (which put tests/ on sys.path) stop with one line
instead: ``real_files_or_exit``; pytest is imported only by the test helpers.
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REAL = (ROOT / os.environ.get("OMNILIDAR_REAL_DATA", "../shared/data/real")).resolve()
REASON = f"real LiDAR samples not found at {REAL} (set OMNILIDAR_REAL_DATA)"

# The sample files, relative to REAL (its README.md says where each comes from).
KITTI_OBJECT = tuple(f"kitti_object/{sub}/00000{i}.{ext}" for i in (0, 1)
                     for sub, ext in (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt")))
KITTI_SCANS = ("kitti_object/velodyne/000000.bin", "kitti_object/velodyne/000001.bin")
SEMANTICKITTI_SCAN = "semantickitti/sequences/00/velodyne/000000.bin"
SEMANTICKITTI_TINY = ("semantickitti_tiny/sequences/00/velodyne/000000.bin",
                      "semantickitti_tiny/sequences/00/labels/000000.label")
NUSCENES_SWEEP = "nuscenes/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
ALL_SAMPLES = (*KITTI_OBJECT, SEMANTICKITTI_SCAN, *SEMANTICKITTI_TINY, NUSCENES_SWEEP)


def _flatten(files) -> list[str]:
    out = []
    for f in files:
        out.extend([f] if isinstance(f, (str, Path)) else _flatten(f))
    return [str(f) for f in out]


def skip_reason(*files) -> str | None:
    """Why a test that reads ``files`` (relative to REAL) cannot run, or None when it can."""
    if not REAL.is_dir():
        return REASON
    absent = [f for f in _flatten(files) if not (REAL / f).is_file()]
    return f"real LiDAR samples at {REAL} lack {', '.join(absent)} (set OMNILIDAR_REAL_DATA)" if absent else None


def needs_real(*files):
    """Mark for tests that read ``files``: @needs_real(KITTI_SCANS) or pytestmark = needs_real(...)."""
    import pytest

    reason = skip_reason(*files)
    return pytest.mark.skipif(reason is not None, reason=reason or "")


def require_real(*files) -> Path:
    """The samples' folder; skips the calling test (or fixture's tests) unless ``files`` are all there."""
    import pytest

    reason = skip_reason(*files)
    if reason is not None:
        pytest.skip(reason)
    return REAL


def real_file(name: str) -> Path:
    """The path of one sample file; skips the calling test when it is absent."""
    return require_real(name) / name


def real_files_or_exit(*files) -> list[Path]:
    """For benchmarks: the samples' paths, or exit with one line saying what is missing."""
    reason = skip_reason(*files)
    if reason is not None:
        raise SystemExit(f"error: {reason}")
    return [REAL / f for f in _flatten(files)]
