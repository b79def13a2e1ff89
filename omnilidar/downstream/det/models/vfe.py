"""Voxel feature encoders (OpenPCDet vfe): MeanVFE."""

from __future__ import annotations

from torch import nn


class MeanVFE(nn.Module):
    """A voxel's feature is the mean of its points (no parameters)."""

    def __init__(self, model_cfg: dict, num_point_features: int, **_):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_point_features = num_point_features

    def get_output_feature_dim(self) -> int:
        return self.num_point_features

    def forward(self, batch_dict: dict) -> dict:
        voxels, counts = batch_dict["voxels"], batch_dict["voxel_num_points"]
        total = voxels.sum(dim=1)
        batch_dict["voxel_features"] = total / counts.clamp(min=1).view(-1, 1).type_as(voxels)
        return batch_dict
