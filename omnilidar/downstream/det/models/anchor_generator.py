"""OpenPCDet's AnchorGenerator: per class, anchors on the BEV feature grid."""

from __future__ import annotations

import torch


def generate_anchors(anchor_range, anchor_configs: list[dict], grid_size) -> tuple[list[torch.Tensor], list[int]]:
    """Per anchor config, a (Z, Y, X, num_sizes, num_rotations, 7) tensor of
    anchors (z at the box centre), and the anchors per BEV location of each.

    ``grid_size`` is the voxel grid (X, Y, Z); each config's ``feature_map_stride``
    gives its feature map. Without ``align_center`` the first and last anchors
    sit on the range's edges (OpenPCDet's default), with it on cell centres.
    """
    anchors_list, per_location = [], []
    for cfg in anchor_configs:
        stride = int(cfg["feature_map_stride"])
        nx, ny = int(grid_size[0]) // stride, int(grid_size[1]) // stride
        sizes = torch.tensor(cfg["anchor_sizes"], dtype=torch.float32).view(-1, 3)
        rotations = torch.tensor(cfg["anchor_rotations"], dtype=torch.float32).view(-1)
        bottoms = torch.tensor(cfg["anchor_bottom_heights"], dtype=torch.float32).view(-1)
        per_location.append(len(sizes) * len(rotations) * len(bottoms))
        if cfg.get("align_center", False):
            sx, sy = (anchor_range[3] - anchor_range[0]) / nx, (anchor_range[4] - anchor_range[1]) / ny
            ox, oy = sx / 2, sy / 2
        else:
            sx, sy = (anchor_range[3] - anchor_range[0]) / (nx - 1), (anchor_range[4] - anchor_range[1]) / (ny - 1)
            ox, oy = 0.0, 0.0
        xs = torch.arange(anchor_range[0] + ox, anchor_range[3] + 1e-5, step=sx, dtype=torch.float32)
        ys = torch.arange(anchor_range[1] + oy, anchor_range[4] + 1e-5, step=sy, dtype=torch.float32)
        gx, gy, gz = torch.meshgrid(xs, ys, bottoms, indexing="ij")
        centres = torch.stack([gx, gy, gz], dim=-1)  # (X, Y, Z, 3)
        shape = (*centres.shape[:3], len(sizes), len(rotations))
        anchors = torch.cat([
            centres[:, :, :, None, None, :].expand(*shape, 3),
            sizes[None, None, None, :, None, :].expand(*shape, 3),
            rotations[None, None, None, None, :, None].expand(*shape, 1),
        ], dim=-1)
        anchors = anchors.permute(2, 1, 0, 3, 4, 5).contiguous()
        anchors[..., 2] += anchors[..., 5] / 2
        anchors_list.append(anchors)
    return anchors_list, per_location
