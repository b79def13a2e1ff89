"""SemanticKITTI: ``sequences/NN/velodyne/XXXXXX.bin`` and ``labels/XXXXXX.label``.

Scans are float32 little-endian records x, y, z, remission (remission 0..1).
Labels are uint32 per point: semantic = label & 0xFFFF, instance = label >> 16.

Reading policy (see tests/test_io_bad_input.py):

- ``read_points`` is the raw reader: it checks the file size and that every
  value is finite, and returns (N, 4) float32 (N may be 0).
- ``read_scan`` builds a :class:`Scan` and is strict: an empty sweep (0 points)
  is an error, because a spinning LiDAR always returns something and an empty
  file means a truncated copy or a failed export; remission must lie in 0..1
  (a nuScenes file read as KITTI, or a 0..255 export, fails here).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io import pointfile
from omnilidar.lidar.scan import Scan

POINT_LAYOUT = "float32 x,y,z,remission"
LABEL_LAYOUT = "uint32 semantic | instance << 16"

# Official semantic-kitti-api learning map (config/semantic-kitti.yaml): raw id -> train id.
LEARNING_MAP: dict[int, int] = {
    0: 0, 1: 0, 52: 0, 99: 0,  # unlabeled, outlier, other-structure, other-object -> ignore
    10: 1, 252: 1,  # car, moving-car
    11: 2,  # bicycle
    15: 3,  # motorcycle
    18: 4, 258: 4,  # truck, moving-truck
    13: 5, 16: 5, 20: 5, 256: 5, 257: 5, 259: 5,  # bus, on-rails, other-vehicle (+ moving)
    30: 6, 254: 6,  # person, moving-person
    31: 7, 253: 7,  # bicyclist, moving-bicyclist
    32: 8, 255: 8,  # motorcyclist, moving-motorcyclist
    40: 9, 60: 9,  # road, lane-marking
    44: 10,  # parking
    48: 11,  # sidewalk
    49: 12,  # other-ground
    50: 13,  # building
    51: 14,  # fence
    70: 15,  # vegetation
    71: 16,  # trunk
    72: 17,  # terrain
    80: 18,  # pole
    81: 19,  # traffic-sign
}

# Train id -> canonical raw id (official learning_map_inv).
LEARNING_MAP_INV: dict[int, int] = {
    0: 0, 1: 10, 2: 11, 3: 15, 4: 18, 5: 20, 6: 30, 7: 31, 8: 32, 9: 40,
    10: 44, 11: 48, 12: 49, 13: 50, 14: 51, 15: 70, 16: 71, 17: 72, 18: 80, 19: 81,
}

# Names of train ids 1..19 (CLASS_NAMES[i - 1] is train id i; 0 is ignore).
CLASS_NAMES: tuple[str, ...] = (
    "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist",
    "motorcyclist", "road", "parking", "sidewalk", "other-ground", "building", "fence",
    "vegetation", "trunk", "terrain", "pole", "traffic-sign",
)
NUM_CLASSES = len(CLASS_NAMES) + 1  # with ignore (0)

SPLITS: dict[str, list[str]] = {
    "train": ["00", "01", "02", "03", "04", "05", "06", "07", "09", "10"],
    "val": ["08"],
    "test": [f"{i:02d}" for i in range(11, 22)],
}

_TRAIN_LUT = np.zeros(1 << 16, dtype=np.uint8)  # unknown raw ids -> 0 (ignore)
for _raw, _train in LEARNING_MAP.items():
    _TRAIN_LUT[_raw] = _train
_TRAIN_LUT.setflags(write=False)
_RAW_LUT = np.array([LEARNING_MAP_INV[i] for i in range(NUM_CLASSES)], dtype=np.uint16)
_RAW_LUT.setflags(write=False)


def to_train_ids(semantic: np.ndarray) -> np.ndarray:
    """Map raw semantic ids (uint16, label & 0xFFFF) to train ids 0..19 (uint8).

    Raw ids that are not in the official map become 0 (ignore).
    """
    semantic = np.asarray(semantic)
    if semantic.dtype.kind not in "iu":
        raise InputError(None, f"semantic ids must be integers, got dtype {semantic.dtype}")
    if semantic.size and (semantic.min() < 0 or semantic.max() > 0xFFFF):
        raise InputError(None, "semantic ids must lie in 0..65535 (did you pass packed uint32 labels?)")
    return _TRAIN_LUT[semantic]


def to_raw_ids(train_ids: np.ndarray) -> np.ndarray:
    """Map train ids 0..19 to canonical raw SemanticKITTI ids (uint16)."""
    train_ids = np.asarray(train_ids)
    if train_ids.dtype.kind not in "iu":
        raise InputError(None, f"train ids must be integers, got dtype {train_ids.dtype}")
    if train_ids.size and (train_ids.min() < 0 or train_ids.max() >= NUM_CLASSES):
        raise InputError(
            None, f"train ids must lie in 0..{NUM_CLASSES - 1}, found {train_ids.min()}..{train_ids.max()}"
        )
    return _RAW_LUT[train_ids]


def read_points(path: str | Path) -> np.ndarray:
    """Read a KITTI-format ``.bin`` as (N, 4) float32 x, y, z, remission.

    Raises InputError for a missing file, a size that is not a whole number of
    16-byte records, or NaN/infinite values. An empty file gives (0, 4).
    """
    points = pointfile.read_records(path, "<f4", 4, POINT_LAYOUT)
    pointfile.check_finite(path, points, "coordinates or remission")
    return points.astype(np.float32, copy=False)


def write_points(path: str | Path, points: np.ndarray) -> None:
    """Write (N, 4) x, y, z, remission as a float32 ``.bin``, atomically."""
    points = pointfile.as_float_matrix(path, points, 4, "points")
    pointfile.write_records(path, points, "<f4")


def read_label(path: str | Path, num_points: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``.label`` file; return (semantic uint16, instance uint16).

    With ``num_points`` the label count must match the scan's point count.
    """
    labels = pointfile.read_records(path, "<u4", 1, LABEL_LAYOUT)[:, 0]
    if num_points is not None and len(labels) != num_points:
        raise InputError(path, f"has {len(labels)} labels but its scan has {num_points} points")
    semantic = (labels & 0xFFFF).astype(np.uint16)
    instance = (labels >> 16).astype(np.uint16)
    return semantic, instance


def write_label(path: str | Path, semantic: np.ndarray, instance: np.ndarray | None = None) -> None:
    """Write uint32 labels ``semantic | instance << 16``, atomically.

    ``instance`` None writes instance 0 for every point.
    """
    semantic = pointfile.as_uint_vector(path, semantic, 16, "semantic ids")
    if instance is None:
        instance = np.zeros(len(semantic), np.uint16)
    instance = pointfile.as_uint_vector(path, instance, 16, "instance ids", length=len(semantic))
    packed = semantic.astype(np.uint32) | (instance.astype(np.uint32) << 16)
    pointfile.write_records(path, packed, "<u4")


def _check_scan_points(path, points: np.ndarray) -> None:
    if len(points) == 0:
        raise InputError(path, "scan has 0 points (an empty sweep means a truncated or failed export)")
    pointfile.check_range(
        path, points[:, 3], 0.0, 1.0, "remission",
        hint="; KITTI remission is 0..1 (is this a 0..255 or a 5-column nuScenes file?)",
    )


def read_scan(bin_path: str | Path, label_path: str | Path | None = None) -> Scan:
    """Read a scan (and optionally its labels) into a Scan with intensity_scale 1.0."""
    points = read_points(bin_path)
    _check_scan_points(bin_path, points)
    semantic = instance = None
    if label_path is not None:
        semantic, instance = read_label(label_path, num_points=len(points))
    return Scan(points=points, semantic=semantic, instance=instance, intensity_scale=1.0)


def write_scan(scan: Scan, bin_path: str | Path, label_path: str | Path | None = None) -> None:
    """Write a scan as ``.bin`` (remission rescaled to 0..1) and optionally ``.label``.

    Everything is validated before either file is written, so a bad scan
    leaves neither file behind.
    """
    points = pointfile.as_float_matrix(bin_path, scan.points, 4, "points")  # a fresh copy
    if scan.intensity_scale != 1.0:
        points[:, 3] /= np.float32(scan.intensity_scale)
    _check_scan_points(bin_path, points)
    if label_path is not None and scan.semantic is None:
        raise InputError(label_path, "scan has no semantic labels to write")
    write_points(bin_path, points)
    if label_path is not None:
        write_label(label_path, scan.semantic, scan.instance)


def _sequence_name(sequence: str | int) -> str:
    text = str(sequence).strip()
    if not text.isdigit():
        raise InputError(None, f"SemanticKITTI sequence must be a number like '08', got {sequence!r}")
    return f"{int(text):02d}"


def sequence_paths(root: str | Path, sequence: str) -> list[tuple[Path, Path | None]]:
    """(scan, label or None) pairs of one sequence, sorted by frame.

    ``root`` is the dataset root holding ``sequences/``. A sequence without a
    ``labels/`` folder (test split) gives None labels; a labels folder that
    lacks some scans' labels, or holds labels without scans, is an error.
    """
    root = pointfile.require_dir(root, "SemanticKITTI root")
    seq_dir = pointfile.require_dir(root / "sequences" / _sequence_name(sequence), "sequence folder")
    velo_dir = pointfile.require_dir(seq_dir / "velodyne", "velodyne folder")
    scans = sorted(velo_dir.glob("*.bin"))
    if not scans:
        raise InputError(velo_dir, "holds no .bin scans")
    label_dir = seq_dir / "labels"
    if not label_dir.is_dir():
        return [(scan, None) for scan in scans]
    labels = {p.stem: p for p in label_dir.glob("*.label")}
    stems = {s.stem for s in scans}
    missing = sorted(stems - set(labels))
    orphans = sorted(set(labels) - stems)
    if missing:
        raise InputError(label_dir, f"{len(missing)} scans have no label (first: {missing[0]}.label)")
    if orphans:
        raise InputError(label_dir, f"{len(orphans)} labels have no scan (first: {orphans[0]}.label)")
    return [(scan, labels[scan.stem]) for scan in scans]
