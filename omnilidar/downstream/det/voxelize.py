"""Points -> voxels as OpenPCDet's ``transform_points_to_voxels`` (spconv's point-to-voxel).

Points are visited in their order: a point outside the grid is dropped; the
first point that falls into a new voxel opens it (voxels numbered in order of
opening, at most ``max_voxels``, later new voxels are dropped with their
points); each voxel keeps its first ``max_points`` points. Voxels are
zero-padded ``(V, max_points, C)`` arrays with ``num_points`` (V,) and integer
coordinates ``(V, 3)`` as ``[z, y, x]``, the layout MeanVFE and the sparse
backbone read. Vectorised numpy, no Python loop over points.
"""

from __future__ import annotations

import numpy as np


def points_to_voxels(points: np.ndarray, voxel_size, point_cloud_range, max_points: int,
                     max_voxels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(voxels (V, max_points, C) float32, coords (V, 3) int32 [z, y, x], num_points (V,) int32)``."""
    points = np.asarray(points, np.float32)
    channels = points.shape[1]
    vs = np.asarray(voxel_size, np.float32)
    lo = np.asarray(point_cloud_range[:3], np.float32)
    grid = np.round((np.asarray(point_cloud_range[3:6], np.float32) - lo) / vs).astype(np.int64)
    cell = np.floor((points[:, :3] - lo) / vs).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < grid), axis=1)
    order = np.flatnonzero(inside)
    if order.size == 0:
        return (np.zeros((0, max_points, channels), np.float32), np.zeros((0, 3), np.int32),
                np.zeros(0, np.int32))
    cell = cell[order]
    key = (cell[:, 2] * grid[1] + cell[:, 1]) * grid[0] + cell[:, 0]
    uniq, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    # Voxel ids in order of first appearance.
    opening = np.argsort(first, kind="stable")
    voxel_of_uniq = np.empty_like(opening)
    voxel_of_uniq[opening] = np.arange(len(opening))
    voxel = voxel_of_uniq[inverse.reshape(-1)]
    # Rank of each point within its voxel (points stay in their order).
    by_voxel = np.argsort(voxel, kind="stable")
    sorted_voxel = voxel[by_voxel]
    starts = np.searchsorted(sorted_voxel, sorted_voxel, side="left")
    rank = np.empty_like(voxel)
    rank[by_voxel] = np.arange(len(voxel)) - starts
    keep = (voxel < max_voxels) & (rank < max_points)
    count = min(len(opening), int(max_voxels))
    voxels = np.zeros((count, max_points, channels), np.float32)
    voxels[voxel[keep], rank[keep]] = points[order[keep]]
    num_points = np.minimum(np.bincount(voxel[voxel < max_voxels], minlength=count), max_points).astype(np.int32)
    first_point = order[first[opening[:count]]]
    xyz = np.floor((points[first_point, :3] - lo) / vs).astype(np.int32)
    coords = xyz[:, ::-1].copy()
    return voxels, coords, num_points
