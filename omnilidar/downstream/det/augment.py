"""Training augmentations of OpenPCDet's KITTI / Pi3DET configs, applied to points and boxes together.

In the order of Pi3DET's dataset config: random object rotation (ST3D's
``rotate_objects``: each box with probability p turns about its own centre by
the first of 50 draws from U[lo, hi] that overlaps no other box in BEV; the
points inside it turn with it and background points the turned box now covers
are dropped), random world flip along x (y -> -y, heading -> -heading,
probability 0.5), random world rotation about z by U[lo, hi] (points and box
centres rotate counter-clockwise, headings add the angle), random world scaling
by U[lo, hi] (coordinates and box sizes). Ground-truth sampling is not
implemented (Pi3DET's config does not use it). Every draw comes from the
generator passed in.
"""

from __future__ import annotations

import numpy as np
import torch

from omnilidar.geometry.rotated_iou import boxes_iou_bev
from omnilidar.geometry.points_in_boxes import points_in_boxes_mask

OBJECT_ROTATION_TRIES = 50  # ST3D / Pi3DET num_try
_CIRCLE_MARGIN = 0.01  # m


def _inside(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(N,) bool: points inside one box."""
    return points_in_boxes_mask(torch.from_numpy(np.ascontiguousarray(points[:, :3], np.float32)),
                                torch.from_numpy(box.reshape(1, 7).astype(np.float32)))[:, 0].numpy()


def rotate_objects(points: np.ndarray, boxes: np.ndarray, probability: float, noise: tuple[float, float],
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Turn boxes (and their points) about their own centres where the turned box collides with no other."""
    n = len(boxes)
    chosen = rng.uniform(0, 1, n) < probability
    angles = rng.uniform(noise[0], noise[1], (n, OBJECT_ROTATION_TRIES))
    points, boxes = points.copy(), boxes.copy()
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])  # BEV circle around each box
    for k in np.flatnonzero(chosen):
        tries = np.repeat(boxes[k:k + 1], OBJECT_ROTATION_TRIES, axis=0)
        tries[:, 6] += angles[k]
        first = 0
        close = np.hypot(boxes[:, 0] - boxes[k, 0], boxes[:, 1] - boxes[k, 1]) <= radius + radius[k] + _CIRCLE_MARGIN
        close[k] = False  # only boxes whose BEV circles meet this one's can overlap it
        if close.any():
            others = boxes[close]
            overlap = boxes_iou_bev(torch.from_numpy(tries.astype(np.float32)),
                                    torch.from_numpy(others.astype(np.float32))).amax(dim=1).numpy()
            free = np.flatnonzero(overlap == 0)
            if len(free) == 0:
                continue
            first = int(free[0])
        # Only points within the box's BEV circle (the same before and after the turn,
        # widened for rounding) can be inside it; the exact test runs on those.
        near = np.flatnonzero(np.hypot(points[:, 0] - boxes[k, 0], points[:, 1] - boxes[k, 1])
                              <= radius[k] + _CIRCLE_MARGIN)
        was_inside = near[_inside(points[near], boxes[k])]
        c, s = np.cos(angles[k, first]), np.sin(angles[k, first])
        d = points[was_inside, :2].astype(np.float64) - boxes[k, :2]
        points[was_inside, 0] = d[:, 0] * c - d[:, 1] * s + boxes[k, 0]
        points[was_inside, 1] = d[:, 0] * s + d[:, 1] * c + boxes[k, 1]
        inside_before = np.zeros(len(near), bool)
        inside_before[np.searchsorted(near, was_inside)] = True
        changed = near[_inside(points[near], tries[first]) != inside_before]
        points = np.delete(points, changed, axis=0)
        boxes[k] = tries[first]
    return points, boxes


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
    """Apply the configured augmentations (``object_rotation``, ``flip_x``, ``rotation``, ``scaling``) in order."""
    objects = settings.get("object_rotation")
    if objects and objects["probability"] > 0 and len(boxes):
        points, boxes = rotate_objects(points, boxes, objects["probability"], objects["range"], rng)
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
