"""HeightCompression (OpenPCDet map_to_bev): stack the z slices of the sparse
output into BEV channels."""

from __future__ import annotations

from torch import nn


class HeightCompression(nn.Module):
    def __init__(self, model_cfg: dict, **_):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_bev_features = int(model_cfg["NUM_BEV_FEATURES"])

    def forward(self, batch_dict: dict) -> dict:
        dense = batch_dict["encoded_spconv_tensor"].dense()  # (B, C, Z, Y, X)
        b, c, d, h, w = dense.shape
        if c * d != self.num_bev_features:
            raise ValueError(f"NUM_BEV_FEATURES is {self.num_bev_features} but the 3D backbone gives "
                             f"{c} channels x {d} z slices = {c * d}; fix MAP_TO_BEV or the grid")
        batch_dict["spatial_features"] = dense.view(b, c * d, h, w)
        batch_dict["spatial_features_stride"] = batch_dict["encoded_spconv_tensor_stride"]
        return batch_dict
