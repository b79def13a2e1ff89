"""Training augmentations of OpenPCDet's KITTI / Pi3DET configs, applied to points and boxes together.

In OpenPCDet's order: random world flip along x (y -> -y, heading -> -heading,
probability 0.5), random world rotation about z by U[lo, hi] (points and box
centres rotate counter-clockwise, headings add the angle), random world scaling
by U[lo, hi] (coordinates and box sizes). Ground-truth sampling is not
implemented (it is off in the CPU configs; the report says so). Every draw
comes from the generator passed in.
"""

from __future__ import annotations

import numpy as np


def flip_along_x(points: np.ndarray, boxes: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    if rng.random() < 0.5:
        points, boxes = points.copy(), boxes.copy()
        points[:, 1] = -points[:, 1]
        boxes[:, 1] = -boxes[:, 1]
        boxes[:, 6] = -boxes[:, 6]
    return points, boxes


def rotate_about_z(points: np.ndarray, boxes: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(angle), np.sin(angle)
    points, boxes = points.copy(), boxes.copy()
    x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    points[:, 0], points[:, 1] = x * c - y * s, x * s + y * c
    bx, by = boxes[:, 0].astype(np.float64), boxes[:, 1].astype(np.float64)
    boxes[:, 0], boxes[:, 1] = bx * c - by * s, bx * s + by * c
    boxes[:, 6] += angle
    return points, boxes


def scale(points: np.ndarray, boxes: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    points, boxes = points.copy(), boxes.copy()
    points[:, :3] *= factor
    boxes[:, :6] *= factor
    return points, boxes


def augment(points: np.ndarray, boxes: np.ndarray, settings: dict,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Apply the configured augmentations (``flip_x``, ``rotation``, ``scaling``) in OpenPCDet's order."""
    if settings["flip_x"]:
        points, boxes = flip_along_x(points, boxes, rng)
    lo, hi = settings["rotation"]
    if hi > lo:
        points, boxes = rotate_about_z(points, boxes, float(rng.uniform(lo, hi)))
    lo, hi = settings["scaling"]
    if hi > lo:
        points, boxes = scale(points, boxes, float(rng.uniform(lo, hi)))
    return points, boxes


def limit_heading(heading: np.ndarray) -> np.ndarray:
    """Headings into [-pi, pi) (OpenPCDet's limit_period with offset 0.5, period 2 pi)."""
    return heading - np.floor(heading / (2 * np.pi) + 0.5) * 2 * np.pi
