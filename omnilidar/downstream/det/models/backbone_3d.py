"""VoxelBackBone8x (OpenPCDet backbones_3d.spconv_backbone) on omnilidar.sparse convs.

Module names, indices and weight shapes equal OpenPCDet's, so its state dicts load
strictly. Sparse tensors here carry OpenPCDet's voxel order: coords rows
``batch, z, y, x`` and spatial shape ``(Z + 1, Y, X)``; the kernels' axes follow it.
"""

from __future__ import annotations


import torch
from torch import nn

from omnilidar.sparse.backend import conv_layers
from omnilidar.sparse.kernel_map import strided_output_shape
from omnilidar.sparse.tensor import SparseTensor

# OpenPCDet's fixed widths: conv_input/conv1, conv2, conv3, conv4, conv_out.
DEFAULT_WIDTHS = (16, 32, 64, 64, 128)


class SparseSequential(nn.Sequential):
    """Sparse convolutions act on the tensor, everything else on its feature rows."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        for module in self:
            x = module(x) if isinstance(module, SparseSequential) or hasattr(module, "indice_key") \
                else x.replace_feats(module(x.feats))
        return x


def _norm(channels: int) -> nn.BatchNorm1d:
    return nn.BatchNorm1d(channels, eps=1e-3, momentum=0.01)


class VoxelBackBone8x(nn.Module):
    """Four sparse stages (strides 1, 2, 4, 8) and a z-downsampling conv_out.

    ``NUM_FILTERS`` (ours, optional) narrows the five widths for small CPU models;
    without it the widths are OpenPCDet's.
    """

    def __init__(self, model_cfg: dict, input_channels: int, grid_size, sparse_backend: str = "torch", **_):
        super().__init__()
        self.model_cfg = model_cfg
        c0, c2, c3, c4, c_out = model_cfg.get("NUM_FILTERS", DEFAULT_WIDTHS)
        layers = conv_layers(sparse_backend)
        subm, spconv = layers.SubMConv3d, layers.SparseConv3d
        gx, gy, gz = (int(g) for g in grid_size)
        self.sparse_shape = (gz + 1, gy, gx)

        def block(cin, cout, key, stride=1, padding=1):
            conv = subm(cin, cout, 3, indice_key=key) if stride == 1 else \
                spconv(cin, cout, 3, stride=stride, padding=padding, indice_key=key)
            return SparseSequential(conv, _norm(cout), nn.ReLU())

        self.conv_input = SparseSequential(subm(input_channels, c0, 3, padding=1, indice_key="subm1"),
                                           _norm(c0), nn.ReLU())
        self.conv1 = SparseSequential(block(c0, c0, "subm1"))
        self.conv2 = SparseSequential(block(c0, c2, "spconv2", 2), block(c2, c2, "subm2"), block(c2, c2, "subm2"))
        self.conv3 = SparseSequential(block(c2, c3, "spconv3", 2), block(c3, c3, "subm3"), block(c3, c3, "subm3"))
        self.conv4 = SparseSequential(block(c3, c4, "spconv4", 2, (0, 1, 1)),
                                      block(c4, c4, "subm4"), block(c4, c4, "subm4"))
        last_pad = model_cfg.get("last_pad", 0)
        self.conv_out = SparseSequential(
            spconv(c4, c_out, (3, 1, 1), stride=(2, 1, 1), padding=last_pad, indice_key="spconv_down2"),
            _norm(c_out), nn.ReLU())
        self.num_point_features = c_out
        # The output grid (Z, Y, X); HeightCompression sees c_out channels per z slice left.
        shape = self.sparse_shape
        for kernel, stride, padding in ((3, 2, 1), (3, 2, 1), (3, 2, (0, 1, 1)), ((3, 1, 1), (2, 1, 1), last_pad)):
            shape = strided_output_shape(shape, kernel, stride, padding, 1)
        self.out_spatial_shape = shape
        self.num_bev_features = c_out * shape[0]
        self.backbone_channels = {"x_conv1": c0, "x_conv2": c2, "x_conv3": c3, "x_conv4": c4}

    def forward(self, batch_dict: dict) -> dict:
        coords = batch_dict["voxel_coords"].int()
        x = SparseTensor(batch_dict["voxel_features"], coords, self.sparse_shape, int(batch_dict["batch_size"]))
        x = self.conv_input(x)
        x_conv1 = self.conv1(x)
        x_conv2 = self.conv2(x_conv1)
        x_conv3 = self.conv3(x_conv2)
        x_conv4 = self.conv4(x_conv3)
        out = self.conv_out(x_conv4)
        batch_dict["encoded_spconv_tensor"] = out
        batch_dict["encoded_spconv_tensor_stride"] = 8
        batch_dict["multi_scale_3d_features"] = {"x_conv1": x_conv1, "x_conv2": x_conv2,
                                                 "x_conv3": x_conv3, "x_conv4": x_conv4}
        batch_dict["multi_scale_3d_strides"] = {"x_conv1": 1, "x_conv2": 2, "x_conv3": 4, "x_conv4": 8}
        return batch_dict
