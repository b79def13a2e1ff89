"""NeighborVoxelSAModuleMSG (OpenPCDet pointnet2_stack.voxel_pool_modules):
pool sparse voxel features around query points found by voxel query."""

from __future__ import annotations

import torch
from torch import nn

from omnilidar.downstream.det.ops.sampling import VoxelQueryAndGrouping


class NeighborVoxelSAModuleMSG(nn.Module):
    """Per scale: project voxel features (mlps_in), add an embedding of the
    relative positions (mlps_pos), ReLU, max/avg over the neighbours, mlps_out."""

    def __init__(self, *, query_ranges, radii, nsamples, mlps, pool_method: str = "max_pool"):
        super().__init__()
        if not len(query_ranges) == len(radii) == len(nsamples) == len(mlps):
            raise ValueError("QUERY_RANGES, POOL_RADIUS, NSAMPLE and MLPS need one entry per scale")
        if pool_method not in ("max_pool", "avg_pool"):
            raise ValueError(f"POOL_METHOD {pool_method!r} is not max_pool or avg_pool")
        self.groupers = nn.ModuleList()
        self.mlps_in = nn.ModuleList()
        self.mlps_pos = nn.ModuleList()
        self.mlps_out = nn.ModuleList()
        for max_range, radius, nsample, spec in zip(query_ranges, radii, nsamples, mlps):
            self.groupers.append(VoxelQueryAndGrouping(max_range, radius, nsample))
            self.mlps_in.append(nn.Sequential(nn.Conv1d(spec[0], spec[1], 1, bias=False), nn.BatchNorm1d(spec[1])))
            self.mlps_pos.append(nn.Sequential(nn.Conv2d(3, spec[1], 1, bias=False), nn.BatchNorm2d(spec[1])))
            self.mlps_out.append(nn.Sequential(nn.Conv1d(spec[1], spec[2], 1, bias=False),
                                               nn.BatchNorm1d(spec[2]), nn.ReLU()))
        self.relu = nn.ReLU()
        self.pool_method = pool_method
        for m in self.modules():
            if isinstance(m, (nn.Conv1d, nn.Conv2d)):
                nn.init.kaiming_normal_(m.weight)
            elif isinstance(m, (nn.BatchNorm1d, nn.BatchNorm2d)):
                nn.init.constant_(m.weight, 1.0)
                nn.init.constant_(m.bias, 0.0)

    def forward(self, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt, new_coords, features, voxel2point_indices):
        """``new_coords`` (M, 4) [batch, x, y, z] voxel of each query point at this
        scale; ``voxel2point_indices`` (B, Z, Y, X). Returns (M, sum of out widths)."""
        new_coords = new_coords[:, [0, 3, 2, 1]].contiguous()  # -> batch, z, y, x
        outputs = []
        for k, grouper in enumerate(self.groupers):
            projected = self.mlps_in[k](features.t().unsqueeze(0))[0].t().contiguous()
            grouped, grouped_xyz, empty = grouper(new_coords, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt,
                                                  projected, voxel2point_indices)
            keep = (~empty).to(grouped.dtype)[:, None, None]
            grouped = grouped * keep
            rel = (grouped_xyz - new_xyz.unsqueeze(-1)) * keep
            pos = self.mlps_pos[k](rel.permute(1, 0, 2).unsqueeze(0))  # (1, C, M, nsample)
            x = self.relu(grouped.permute(1, 0, 2).unsqueeze(0) + pos)
            x = x.max(dim=-1).values if self.pool_method == "max_pool" else x.mean(dim=-1)
            outputs.append(self.mlps_out[k](x)[0].t())
        return torch.cat(outputs, dim=1)
