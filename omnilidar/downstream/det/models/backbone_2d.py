"""BaseBEVBackbone (OpenPCDet backbones_2d): strided conv blocks, each upsampled
back by a deblock, outputs concatenated."""

from __future__ import annotations

import torch
from torch import nn


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=1e-3, momentum=0.01)


class BaseBEVBackbone(nn.Module):
    def __init__(self, model_cfg: dict, input_channels: int, **_):
        super().__init__()
        self.model_cfg = model_cfg
        layer_nums = list(model_cfg.get("LAYER_NUMS", []))
        layer_strides = list(model_cfg.get("LAYER_STRIDES", []))
        num_filters = list(model_cfg.get("NUM_FILTERS", []))
        up_strides = list(model_cfg.get("UPSAMPLE_STRIDES", []))
        up_filters = list(model_cfg.get("NUM_UPSAMPLE_FILTERS", []))
        if not (len(layer_nums) == len(layer_strides) == len(num_filters)) or len(up_strides) != len(up_filters):
            raise ValueError("BACKBONE_2D: LAYER_NUMS, LAYER_STRIDES, NUM_FILTERS must have one entry per level, "
                             "UPSAMPLE_STRIDES and NUM_UPSAMPLE_FILTERS the same length")
        c_in_list = [input_channels, *num_filters[:-1]]
        self.blocks = nn.ModuleList()
        self.deblocks = nn.ModuleList()
        for i, (n_layers, stride, c_out) in enumerate(zip(layer_nums, layer_strides, num_filters)):
            layers = [nn.ZeroPad2d(1), nn.Conv2d(c_in_list[i], c_out, 3, stride=stride, padding=0, bias=False),
                      _bn(c_out), nn.ReLU()]
            for _ in range(n_layers):
                layers += [nn.Conv2d(c_out, c_out, 3, padding=1, bias=False), _bn(c_out), nn.ReLU()]
            self.blocks.append(nn.Sequential(*layers))
            if up_strides:
                self.deblocks.append(self._deblock(c_out, up_filters[i], up_strides[i],
                                                   bool(model_cfg.get("USE_CONV_FOR_NO_STRIDE", False))))
        c_total = sum(up_filters)
        if len(up_strides) > len(layer_nums):
            self.deblocks.append(nn.Sequential(
                nn.ConvTranspose2d(c_total, c_total, up_strides[-1], stride=up_strides[-1], bias=False),
                _bn(c_total), nn.ReLU()))
        self.num_bev_features = c_total if up_strides else num_filters[-1]

    def output_size(self, height: int, width: int) -> tuple[int, int]:
        """The BEV map size out of a ``height`` x ``width`` input; ValueError when the
        upsampled levels would not line up for concatenation."""
        sizes = []
        h, w = height, width
        for i, block in enumerate(self.blocks):
            conv = block[1]
            h, w = (h + 2 - 3) // conv.stride[0] + 1, (w + 2 - 3) // conv.stride[1] + 1
            if len(self.deblocks) > 0:
                up = self.deblocks[i][0]
                if isinstance(up, nn.ConvTranspose2d):
                    sizes.append((h * up.stride[0], w * up.stride[1]))
                else:
                    sizes.append(((h - up.kernel_size[0]) // up.stride[0] + 1, (w - up.kernel_size[1]) // up.stride[1] + 1))
            else:
                sizes.append((h, w))
        if len(set(sizes)) > 1:
            raise ValueError(f"BACKBONE_2D: a {height} x {width} BEV map gives levels of sizes {sizes}, which cannot be "
                             f"concatenated; make the BEV grid (voxels / 8) divisible by the product of LAYER_STRIDES")
        h, w = sizes[-1]
        if len(self.deblocks) > len(self.blocks):
            up = self.deblocks[-1][0]
            h, w = h * up.stride[0], w * up.stride[1]
        return h, w

    @staticmethod
    def _deblock(c_in: int, c_out: int, stride: float, conv_for_no_stride: bool) -> nn.Sequential:
        if stride > 1 or (stride == 1 and not conv_for_no_stride):
            conv = nn.ConvTranspose2d(c_in, c_out, int(stride), stride=int(stride), bias=False)
        else:
            k = int(round(1 / stride))
            conv = nn.Conv2d(c_in, c_out, k, stride=k, bias=False)
        return nn.Sequential(conv, _bn(c_out), nn.ReLU())

    def forward(self, batch_dict: dict) -> dict:
        x = batch_dict["spatial_features"]
        ups = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            ups.append(self.deblocks[i](x) if len(self.deblocks) > 0 else x)
        x = torch.cat(ups, dim=1) if len(ups) > 1 else ups[0]
        if len(self.deblocks) > len(self.blocks):
            x = self.deblocks[-1](x)
        batch_dict["spatial_features_2d"] = x
        return batch_dict
