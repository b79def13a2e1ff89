"""Regular grids of points inside RoIs (the sampling points of RoI-grid pooling)."""

from __future__ import annotations

import torch


def rotate_points_along_z(points: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate ``(B, N, 3)`` points counter-clockwise by ``angle`` ``(B,)`` about z."""
    cos, sin = torch.cos(angle)[:, None], torch.sin(angle)[:, None]
    x, y = points[..., 0], points[..., 1]
    return torch.stack([x * cos - y * sin, x * sin + y * cos, points[..., 2]], dim=-1)


def roi_grid_points(rois: torch.Tensor, grid_size: int) -> torch.Tensor:
    """Grid cell centres of every RoI in the lidar frame: ``(R, G^3, 3)``.

    rois: ``(R, 7+)``. Grid order is x-major, then y, then z (OpenPCDet's order,
    which fixes the layout of the flattened pooled features).
    """
    steps = torch.arange(grid_size, device=rois.device, dtype=rois.dtype)
    gx, gy, gz = torch.meshgrid(steps, steps, steps, indexing="ij")
    cells = torch.stack([gx, gy, gz], dim=-1).view(1, -1, 3)
    size = rois[:, None, 3:6]
    local = (cells + 0.5) / grid_size * size - size / 2
    return rotate_points_along_z(local, rois[:, 6]) + rois[:, None, 0:3]
