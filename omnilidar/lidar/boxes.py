"""Geometry of lidar-frame 3D boxes (x, y, z_center, dx, dy, dz, heading).

``dx`` is the box length along its heading, ``dy`` its width, ``dz`` its
height; ``heading`` is the yaw (rad) of the box's x axis, counter-clockwise
from the lidar x axis, about z.
"""

from __future__ import annotations

import numpy as np

# Slack (m) of the float32 bounding-square prefilter; the exact test decides.
_PREFILTER_MARGIN = 1e-3


def _as_boxes(boxes) -> np.ndarray:
    arr = getattr(boxes, "boxes", boxes)  # Boxes or a plain (M, 7) array
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ValueError(f"boxes must be (M, 7), got {arr.shape}")
    return arr


def points_in_boxes(points: np.ndarray, boxes) -> np.ndarray:
    """(N, M) bool: point n lies inside box m (faces inclusive).

    ``points`` is (N, >=3) (only x, y, z are used); ``boxes`` is a Boxes or an
    (M, 7) array. Per box, one vectorised pass over x picks the points within
    the box's bounding square, and the exact rotated test (float64) runs on
    those candidates only: O(N M) cheap compares plus work proportional to
    the points near boxes, with no (N, M) float temporaries.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got {pts.shape}")
    b = _as_boxes(boxes)
    n, m = len(pts), len(b)
    out = np.zeros((n, m), dtype=bool)
    if n == 0 or m == 0:
        return out
    x = np.ascontiguousarray(pts[:, 0], dtype=np.float32)
    y = np.ascontiguousarray(pts[:, 1], dtype=np.float32)
    reach = 0.5 * np.hypot(b[:, 3], b[:, 4]) + _PREFILTER_MARGIN  # half diagonal in x-y
    for j, (cx, cy, cz, dx, dy, dz, heading) in enumerate(b):
        cand = np.flatnonzero(np.abs(x - np.float32(cx)) <= reach[j])
        cand = cand[np.abs(y[cand] - np.float32(cy)) <= reach[j]]
        if cand.size == 0:
            continue
        p = pts[cand, :3].astype(np.float64)
        ox, oy = p[:, 0] - cx, p[:, 1] - cy
        c, s = np.cos(heading), np.sin(heading)
        inside = (
            (np.abs(ox * c + oy * s) <= 0.5 * dx)
            & (np.abs(oy * c - ox * s) <= 0.5 * dy)
            & (np.abs(p[:, 2] - cz) <= 0.5 * dz)
        )
        out[cand[inside], j] = True
    return out


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
