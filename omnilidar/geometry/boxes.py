"""Geometry of lidar-frame 3D boxes (x, y, z_center, dx, dy, dz, heading).

``dx`` is the box length along its heading, ``dy`` its width, ``dz`` its
height; ``heading`` is the yaw (rad) of the box's x axis, counter-clockwise
from the lidar x axis, about z.
"""

from __future__ import annotations

import numpy as np
import torch

from omnilidar.geometry.points_in_boxes import points_in_boxes_mask


def _as_boxes(boxes) -> np.ndarray:
    arr = getattr(boxes, "boxes", boxes)  # Boxes or a plain (M, 7) array
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ValueError(f"boxes must be (M, 7), got {arr.shape}")
    return arr


def points_in_boxes(points: np.ndarray, boxes) -> np.ndarray:
    """(N, M) bool: point n lies inside box m (faces inclusive).

    ``points`` is (N, >=3) (only x, y, z are used); ``boxes`` is a Boxes or an
    (M, 7) array. The numpy face of the detection operator
    ``omnilidar.geometry.points_in_boxes.points_in_boxes_mask`` (one
    implementation: a float32 bounding-square prefilter, then the exact rotated
    test in float64 on the candidates only).
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got {pts.shape}")
    b = _as_boxes(boxes)
    xyz = pts[:, :3] if pts.dtype in (np.float32, np.float64) else pts[:, :3].astype(np.float64)
    return points_in_boxes_mask(torch.from_numpy(np.ascontiguousarray(xyz)), torch.from_numpy(b)).numpy()


def box_corners(boxes) -> np.ndarray:
    """(M, 8, 3) corners of each box. Corners 0-3 are the bottom face and 4-7
    the top face, each counter-clockwise from (+dx/2, +dy/2) seen from above."""
    b = _as_boxes(boxes)
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    local_xy = signs[None, :, :] * (0.5 * b[:, None, 3:5])  # (M, 4, 2)
    cos, sin = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    x = b[:, None, 0] + local_xy[..., 0] * cos - local_xy[..., 1] * sin
    y = b[:, None, 1] + local_xy[..., 0] * sin + local_xy[..., 1] * cos
    z_bottom = np.broadcast_to((b[:, 2] - 0.5 * b[:, 5])[:, None], x.shape)
    z_top = np.broadcast_to((b[:, 2] + 0.5 * b[:, 5])[:, None], x.shape)
    bottom = np.stack([x, y, z_bottom], axis=-1)
    top = np.stack([x, y, z_top], axis=-1)
    return np.concatenate([bottom, top], axis=1)
