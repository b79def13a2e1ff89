"""KITTI object labels (``label_2/*.txt``) and calibration (``calib/*.txt``).

A label line has 15 fields (16 with a detection score)::

    type truncated occluded alpha left top right bottom h w l x y z rotation_y [score]

``x, y, z`` is the box's BOTTOM centre in the rectified camera-0 frame
(x right, y down, z forward) and ``rotation_y`` its yaw about the camera y axis.
Our lidar-frame boxes are (x, y, z_center, dx, dy, dz, heading) with
dx = l, dy = w, dz = h and heading = -(rotation_y + pi/2), wrapped to [-pi, pi).

The camera-to-lidar transform is the exact inverse of
``R0_rect @ Tr_velo_to_cam`` (both padded to 4x4), not the transpose
shortcut, so rectification is undone properly.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io import pointfile
from omnilidar.io.atomic import write_text_atomic
from omnilidar.geometry.boxes import box_corners
from omnilidar.lidar.scan import Boxes

CALIB_SHAPES: dict[str, tuple[int, int]] = {
    "P0": (3, 4), "P1": (3, 4), "P2": (3, 4), "P3": (3, 4),
    "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4), "Tr_imu_to_velo": (3, 4),
}
# KITTI tracking / raw files spell some keys differently.
CALIB_ALIASES: dict[str, str] = {
    "R_rect": "R0_rect", "Tr_velo_cam": "Tr_velo_to_cam", "Tr_imu_velo": "Tr_imu_to_velo",
}
CALIB_REQUIRED: tuple[str, ...] = ("R0_rect", "Tr_velo_to_cam")
_ROTATION_TOL = 1e-3  # |R R^T - I| bound: KITTI prints 7 significant digits

DONT_CARE = "DontCare"
# Camera-projected boxes closer than this (or behind the camera) get no 2D box.
_MIN_DEPTH = 0.1


@dataclass(frozen=True)
class KittiObject:
    """One line of a KITTI label file (camera frame, see module docstring)."""

    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox2d: tuple[float, float, float, float]  # left, top, right, bottom (pixels)
    dimensions: tuple[float, float, float]  # h, w, l (m)
    location: tuple[float, float, float]  # bottom centre x, y, z (m, rectified camera)
    rotation_y: float
    score: float | None = None


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to [-pi, pi)."""
    return (np.asarray(angle, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi


# ---------------------------------------------------------------- calibration


def _parse_floats(path, lineno: int, text: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise InputError(path, f"line {lineno}: non-numeric value in {text.strip()[:60]!r}") from None
    if not np.isfinite(values).all():
        raise InputError(path, f"line {lineno}: NaN or infinite value")
    return values


def _check_rotation(path, key: str, rot: np.ndarray) -> None:
    err = np.abs(rot @ rot.T - np.eye(3)).max()
    if err > _ROTATION_TOL or np.linalg.det(rot) <= 0:
        raise InputError(path, f"{key}: rotation part is not a proper rotation (|R R^T - I| = {err:.2g})")


def _read_text(path) -> str:
    path = pointfile.require_file(path)
    try:
        return path.read_text()
    except UnicodeDecodeError:
        raise InputError(path, "is not a text file") from None


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """Read a KITTI calibration file into float64 arrays.

    Known keys get their shapes (P0..P3 3x4, R0_rect 3x3, Tr_velo_to_cam 3x4,
    Tr_imu_to_velo 3x4; tracking spellings R_rect/Tr_velo_cam/Tr_imu_velo are
    renamed); unknown keys are kept as flat arrays. R0_rect and
    Tr_velo_to_cam are required, and their rotations must be orthonormal.
    """
    calib: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(_read_text(path).splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep or not key or " " in key:
            raise InputError(path, f"line {lineno}: expected 'KEY: values', got {line.strip()[:60]!r}")
        key = CALIB_ALIASES.get(key, key)
        if key in calib:
            raise InputError(path, f"line {lineno}: {key} given twice")
        values = _parse_floats(path, lineno, rest)
        shape = CALIB_SHAPES.get(key)
        if shape is not None:
            if values.size != shape[0] * shape[1]:
                raise InputError(
                    path, f"line {lineno}: {key} has {values.size} values, expected {shape[0] * shape[1]}"
                )
            values = values.reshape(shape)
        calib[key] = values
    for key in CALIB_REQUIRED:
        if key not in calib:
            raise InputError(path, f"missing {key}")
    for key in ("R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        if key in calib:
            _check_rotation(path, key, calib[key][:, :3])
    return calib


def write_calib(path: str | Path, calib: dict[str, np.ndarray]) -> None:
    """Write a calibration dict in KITTI object format, atomically (known keys
    first, in KITTI's order)."""
    for key in CALIB_REQUIRED:
        if key not in calib:
            raise InputError(path, f"calibration lacks {key}")
    keys = [k for k in CALIB_SHAPES if k in calib] + [k for k in calib if k not in CALIB_SHAPES]
    lines = []
    for key in keys:
        if not isinstance(key, str) or not key or any(c.isspace() or c == ":" for c in key):
            raise InputError(path, f"bad calibration key {key!r}")
        values = np.asarray(calib[key], dtype=np.float64)
        shape = CALIB_SHAPES.get(key)
        if shape is not None and values.size != shape[0] * shape[1]:
            raise InputError(path, f"{key} has {values.size} values, expected {shape[0] * shape[1]}")
        if not np.isfinite(values).all():
            raise InputError(path, f"{key} holds NaN or infinite values")
        lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in values.ravel()))
    write_text_atomic(path, "\n".join(lines) + "\n")


def _pad4(matrix: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: matrix.shape[0], : matrix.shape[1]] = matrix
    return out


def lidar_to_rect_matrix(calib: dict[str, np.ndarray]) -> np.ndarray:
    """4x4 transform from the lidar frame to the rectified camera-0 frame."""
    return _pad4(np.asarray(calib["R0_rect"])) @ _pad4(np.asarray(calib["Tr_velo_to_cam"]))


def lidar_to_rect(points: np.ndarray, calib: dict[str, np.ndarray]) -> np.ndarray:
    """(N, 3) lidar-frame points -> rectified camera frame (float64)."""
    t = lidar_to_rect_matrix(calib)
    return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


def rect_to_lidar(points: np.ndarray, calib: dict[str, np.ndarray]) -> np.ndarray:
    """(N, 3) rectified-camera points -> lidar frame (float64), exact inverse."""
    t = np.linalg.inv(lidar_to_rect_matrix(calib))
    return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


# --------------------------------------------------------------------- labels


def _parse_object(path, lineno: int, line: str) -> KittiObject:
    fields = line.split()
    if len(fields) not in (15, 16):
        raise InputError(path, f"line {lineno}: {len(fields)} fields, expected 15 (or 16 with a score)")
    values = _parse_floats(path, lineno, " ".join(fields[1:]))
    occluded = values[1]
    if occluded != int(occluded):
        raise InputError(path, f"line {lineno}: occluded must be an integer, got {fields[2]}")
    obj = KittiObject(
        type=fields[0],
        truncated=float(values[0]),
        occluded=int(occluded),
        alpha=float(values[2]),
        bbox2d=tuple(float(v) for v in values[3:7]),
        dimensions=tuple(float(v) for v in values[7:10]),
        location=tuple(float(v) for v in values[10:13]),
        rotation_y=float(values[13]),
        score=float(values[14]) if len(values) == 15 else None,
    )
    if obj.type != DONT_CARE and min(obj.dimensions) <= 0:
        raise InputError(path, f"line {lineno}: {obj.type} has non-positive dimensions {obj.dimensions}")
    return obj


def read_objects(path: str | Path) -> list[KittiObject]:
    """Read a KITTI label file (blank lines skipped; an empty file gives [])."""
    text = _read_text(path)
    return [_parse_object(path, i, line) for i, line in enumerate(text.splitlines(), 1) if line.strip()]


def _format_object(path, obj: KittiObject) -> str:
    if not obj.type or any(c.isspace() for c in obj.type):
        raise InputError(path, f"object type must be one word, got {obj.type!r}")
    if len(obj.bbox2d) != 4 or len(obj.dimensions) != 3 or len(obj.location) != 3:
        raise InputError(path, f"{obj.type}: bbox2d needs 4 values, dimensions and location 3")
    numbers = [obj.truncated, obj.alpha, *obj.bbox2d, *obj.dimensions, *obj.location, obj.rotation_y]
    if obj.score is not None:
        numbers.append(obj.score)
    if not np.isfinite(np.asarray(numbers, dtype=np.float64)).all():
        raise InputError(path, f"{obj.type} object holds NaN or infinite values")
    text = (
        f"{obj.type} {obj.truncated:.2f} {int(obj.occluded):d} {obj.alpha:.4f} "
        + " ".join(f"{v:.2f}" for v in obj.bbox2d) + " "
        + " ".join(f"{v:.4f}" for v in (*obj.dimensions, *obj.location, obj.rotation_y))
    )
    if obj.score is not None:
        text += f" {obj.score:.4f}"
    return text


def write_objects(path: str | Path, objects: Iterable[KittiObject]) -> None:
    """Write objects as a KITTI label file, atomically (4 decimals for 3D values)."""
    lines = [_format_object(path, obj) for obj in objects]
    write_text_atomic(path, "".join(line + "\n" for line in lines))


# ------------------------------------------------------- frame conversions


def objects_to_lidar_boxes(
    objects: Sequence[KittiObject], calib: dict[str, np.ndarray], classes: Iterable[str] | None = None
) -> Boxes:
    """Camera-frame KITTI objects -> lidar-frame Boxes (DontCare skipped).

    ``classes`` keeps only those object types (e.g. ("Car", "Pedestrian")).
    """
    if isinstance(classes, str):
        classes = (classes,)
    wanted = None if classes is None else set(classes)
    kept = [o for o in objects if o.type != DONT_CARE and (wanted is None or o.type in wanted)]
    if not kept:
        return Boxes.empty()
    dims = np.array([o.dimensions for o in kept], dtype=np.float64)  # h, w, l
    bottom = rect_to_lidar(np.array([o.location for o in kept], dtype=np.float64), calib)
    ry = np.array([o.rotation_y for o in kept], dtype=np.float64)
    boxes = np.column_stack([
        bottom[:, 0], bottom[:, 1], bottom[:, 2] + 0.5 * dims[:, 0],
        dims[:, 2], dims[:, 1], dims[:, 0],
        wrap_angle(-(ry + 0.5 * np.pi)),
    ])
    return Boxes(boxes.astype(np.float32), np.array([o.type for o in kept]))


def _image_boxes(boxes: np.ndarray, calib, image_shape) -> np.ndarray:
    """(M, 4) camera-2 image boxes of lidar boxes; -1 where not fully in front."""
    out = np.full((len(boxes), 4), -1.0)
    if "P2" not in calib or len(boxes) == 0:
        return out
    corners = lidar_to_rect(box_corners(boxes).reshape(-1, 3), calib)
    uvw = np.column_stack([corners, np.ones(len(corners))]) @ np.asarray(calib["P2"]).T
    uvw = uvw.reshape(len(boxes), 8, 3)
    front = (uvw[..., 2] > _MIN_DEPTH).all(axis=1)
    uv = uvw[front, :, :2] / uvw[front, :, 2:3]
    rect = np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)
    if image_shape is not None:
        height, width = image_shape
        rect[:, [0, 2]] = np.clip(rect[:, [0, 2]], 0, width - 1)
        rect[:, [1, 3]] = np.clip(rect[:, [1, 3]], 0, height - 1)
    out[front] = rect
    return out


def lidar_boxes_to_objects(
    boxes: Boxes,
    calib: dict[str, np.ndarray],
    scores: np.ndarray | None = None,
    image_shape: tuple[int, int] | None = None,
) -> list[KittiObject]:
    """Lidar-frame Boxes -> KITTI objects (the inverse of objects_to_lidar_boxes).

    ``bbox2d`` is the camera-2 (P2) projection of the box corners, clipped to
    ``image_shape`` (height, width) when given, and (-1, -1, -1, -1) when the
    box is not entirely in front of the camera or calib has no P2 (LiDAR
    boxes cover 360 degrees; the camera sees the front only). ``truncated``
    and ``occluded`` are unknown for LiDAR boxes and written as 0.
    """
    b = np.asarray(boxes.boxes, dtype=np.float64)
    if scores is not None:
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        if len(scores) != len(b):
            raise InputError(None, f"{len(scores)} scores for {len(b)} boxes")
        if not np.isfinite(scores).all():
            raise InputError(None, "scores hold NaN or infinite values")
    if len(b) == 0:
        return []
    bottom = b[:, :3].copy()
    bottom[:, 2] -= 0.5 * b[:, 5]
    loc = lidar_to_rect(bottom, calib)
    ry = wrap_angle(-b[:, 6] - 0.5 * np.pi)
    alpha = wrap_angle(ry - np.arctan2(loc[:, 0], loc[:, 2]))
    image = _image_boxes(b, calib, image_shape)
    return [
        KittiObject(
            type=str(boxes.names[i]),
            truncated=0.0,
            occluded=0,
            alpha=float(alpha[i]),
            bbox2d=tuple(float(v) for v in image[i]),
            dimensions=(float(b[i, 5]), float(b[i, 4]), float(b[i, 3])),
            location=tuple(float(v) for v in loc[i]),
            rotation_y=float(ry[i]),
            score=None if scores is None else float(scores[i]),
        )
        for i in range(len(b))
    ]


def read_boxes_lidar(
    label_path: str | Path, calib_path: str | Path, classes: Iterable[str] | None = None
) -> Boxes:
    """Read a label file and its calibration; return lidar-frame Boxes."""
    return objects_to_lidar_boxes(read_objects(label_path), read_calib(calib_path), classes)
