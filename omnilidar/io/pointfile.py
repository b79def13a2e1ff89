"""Flat binary record files (``.bin`` point clouds, ``.label`` files) and the
checks every reader and writer of them shares.

All LiDAR formats we handle store a point cloud as a headerless little-endian
array of fixed-size records (KITTI: 4 x float32, nuScenes: 5 x float32,
SemanticKITTI labels: 1 x uint32). A reader therefore can only detect
corruption from the file size and the values, so it checks both; a writer
checks the same things before anything touches the disk and then writes
through :mod:`omnilidar.io.atomic`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io.atomic import atomic_path


def require_file(path: str | Path) -> Path:
    """Return ``path`` as a Path, or raise InputError if it is not an existing file."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    if not path.is_file():
        raise InputError(path, "is not a regular file")
    return path


def require_dir(path: str | Path, what: str) -> Path:
    """Return ``path`` as a Path, or raise InputError if it is not a directory."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, f"{what} does not exist" if not path.exists() else f"{what} is not a directory")
    return path


def read_records(path: str | Path, dtype: str, columns: int, layout: str) -> np.ndarray:
    """Read a headerless file of ``columns`` values of ``dtype`` per record.

    Returns an (N, columns) array (N may be 0). ``layout`` describes one record
    for the error message, e.g. ``"float32 x,y,z,remission"``.
    """
    path = require_file(path)
    dt = np.dtype(dtype)
    record = dt.itemsize * columns
    size = path.stat().st_size
    if size % record:
        raise InputError(path, f"size {size} bytes is not a multiple of {record} ({layout})")
    try:
        data = np.fromfile(path, dtype=dt)
    except OSError as err:  # unreadable (permissions, I/O error)
        raise InputError(path, f"cannot be read: {err}") from None
    if data.size * dt.itemsize != size:  # file changed under us
        raise InputError(path, f"read {data.size * dt.itemsize} of {size} bytes")
    return data.reshape(-1, columns)


def check_finite(path: str | Path | None, values: np.ndarray, what: str) -> None:
    """Raise InputError if any row of ``values`` holds NaN or +-inf."""
    if np.isfinite(values).all():  # fast path; the row count below is slower
        return
    bad = ~np.isfinite(values)
    if values.ndim > 1:
        bad = bad.any(axis=1)
    count = int(np.count_nonzero(bad))
    if count:
        first = int(np.flatnonzero(bad)[0])
        raise InputError(
            path, f"{count} of {len(values)} points have NaN or infinite {what} (first at point {first})"
        )


def check_range(path: str | Path | None, values: np.ndarray, low: float, high: float, what: str,
                hint: str = "") -> None:
    """Raise InputError if any value lies outside ``[low, high]``."""
    if values.size == 0 or (values.min() >= low and values.max() <= high):
        return
    bad = (values < low) | (values > high)
    count = int(np.count_nonzero(bad))
    if count:
        lo, hi = float(values.min()), float(values.max())
        raise InputError(
            path,
            f"{count} of {len(values)} points have {what} outside {low:g}..{high:g} "
            f"(found {lo:g}..{hi:g}){hint}",
        )


def as_float_matrix(path: str | Path | None, array, columns: int, what: str) -> np.ndarray:
    """Validate a real numeric (N, columns) array with finite values and return it
    as float32; raise InputError naming ``path`` (the output file) otherwise."""
    array = np.asarray(array)
    if array.dtype.kind not in "fiu":
        raise InputError(path, f"{what} must be a real numeric array, got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] != columns:
        raise InputError(path, f"{what} must have shape (N, {columns}), got {array.shape}")
    with np.errstate(over="ignore"):
        out = array.astype(np.float32)
    # Check after the cast: float64 values beyond float32's range become inf.
    check_finite(path, out, what)
    return out


def as_uint_vector(path: str | Path | None, array, bits: int, what: str, length: int | None = None) -> np.ndarray:
    """Validate a 1-D integer array whose values fit in ``bits`` unsigned bits."""
    array = np.asarray(array)
    if array.dtype.kind not in "iu":
        raise InputError(path, f"{what} must be an integer array, got dtype {array.dtype}")
    if array.ndim != 1:
        raise InputError(path, f"{what} must be 1-D, got shape {array.shape}")
    if length is not None and len(array) != length:
        raise InputError(path, f"{what} has {len(array)} entries for {length} points")
    if array.size:
        lo, hi = int(array.min()), int(array.max())
        if lo < 0 or hi >= 1 << bits:
            raise InputError(path, f"{what} values {lo}..{hi} do not fit in uint{bits}")
    return array


def write_records(path: str | Path, array: np.ndarray, dtype: str) -> None:
    """Write ``array`` as headerless ``dtype`` records, atomically."""
    data = np.ascontiguousarray(array, dtype=np.dtype(dtype))
    with atomic_path(path) as tmp:
        data.tofile(tmp)
