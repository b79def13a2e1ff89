"""Box geometry shared by the detector modules (OpenPCDet's common_utils / box_utils)."""

from __future__ import annotations

import math

import torch


def limit_period(val: torch.Tensor, offset: float = 0.5, period: float = math.pi) -> torch.Tensor:
    """Wrap ``val`` into ``[-offset * period, (1 - offset) * period)``."""
    return val - torch.floor(val / period + offset) * period


def rotate_points_along_z(points: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate ``points`` (B, N, 3 + C) counter-clockwise about z by ``angle`` (B,)."""
    c, s = torch.cos(angle), torch.sin(angle)
    x, y = points[..., 0], points[..., 1]
    xr = x * c[:, None] - y * s[:, None]
    yr = x * s[:, None] + y * c[:, None]
    return torch.cat([xr[..., None], yr[..., None], points[..., 2:]], dim=-1)


# Unit corner signs, bottom face then top face (OpenPCDet's corner order).
_CORNERS = ((1, 1, -1), (1, -1, -1), (-1, -1, -1), (-1, 1, -1),
            (1, 1, 1), (1, -1, 1), (-1, -1, 1), (-1, 1, 1))


def boxes_to_corners_3d(boxes: torch.Tensor) -> torch.Tensor:
    """(N, 7) boxes -> (N, 8, 3) corners."""
    template = boxes.new_tensor(_CORNERS) / 2
    corners = boxes[:, None, 3:6] * template[None]
    corners = rotate_points_along_z(corners, boxes[:, 6])
    return corners + boxes[:, None, 0:3]


def strip_padding(gt_boxes: torch.Tensor) -> torch.Tensor:
    """Drop the trailing all-zero rows of one sample's padded ``gt_boxes``."""
    nonzero = (gt_boxes != 0).any(dim=1).nonzero()
    return gt_boxes[: int(nonzero[-1]) + 1] if len(nonzero) else gt_boxes[:0]


def voxel_centers(coords_zyx: torch.Tensor, stride: int, voxel_size, point_cloud_range) -> torch.Tensor:
    """Centres (N, 3) xyz of voxels at ``coords_zyx`` (N, 3) on a grid ``stride`` times coarser."""
    size = coords_zyx.new_tensor(voxel_size, dtype=torch.float32) * stride
    origin = coords_zyx.new_tensor(point_cloud_range[0:3], dtype=torch.float32)
    return (coords_zyx[:, [2, 1, 0]].float() + 0.5) * size + origin
