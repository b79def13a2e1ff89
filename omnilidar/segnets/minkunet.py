"""MinkUNet (mmdet3d / spvnas layout) on either sparse-convolution backend.

Stem: two 3x3x3 submanifold conv-BN-ReLU. Encoder: four stages, each a
stride-2 kernel-2 conv-BN-ReLU followed by residual blocks (the first changes
the width). Decoder: four stages, each a kernel-2 inverse conv-BN-ReLU back to
the finer level, concatenation with the encoder feature of that level, and
residual blocks. Head: Linear(decoder[-1] -> classes) on voxels.

Widths (REFERENCE section 6): W32 stem 32, encoder [32, 64, 128, 256], decoder
[256, 128, 96, 96]; W16 and W20 scale these by 0.5 and 0.625. Depth 18 uses 2
residual blocks per stage; MinkUNet34 uses [2, 3, 4, 6] in the encoder.

Outputs are logits over the 19 trainable classes: column ``c`` is train id
``c + 1`` (train id 0, ignore, has no column).
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import nn

from omnilidar.segnets.voxelize import SegBatch
from omnilidar.sparse.backend import conv_layers
from omnilidar.sparse.tensor import SparseTensor

NUM_SEG_CLASSES = 19

WIDTHS: dict[str, tuple[int, tuple[int, ...], tuple[int, ...]]] = {
    "W16": (16, (16, 32, 64, 128), (128, 64, 48, 48)),
    "W20": (20, (20, 40, 80, 160), (160, 80, 60, 60)),
    "W32": (32, (32, 64, 128, 256), (256, 128, 96, 96)),
}
ENCODER_BLOCKS: dict[int, tuple[int, ...]] = {18: (2, 2, 2, 2), 34: (2, 3, 4, 6)}
DECODER_BLOCKS = (2, 2, 2, 2)


class SparseBatchNorm(nn.BatchNorm1d):
    """BatchNorm over the voxel feature rows."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace_feats(super().forward(x.feats))


class SparseReLU(nn.ReLU):
    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace_feats(super().forward(x.feats))


class SparseSequential(nn.Sequential):
    """nn.Sequential over SparseTensor-in, SparseTensor-out modules."""


def conv_bn_relu(layers: SimpleNamespace, cin: int, cout: int, kernel: int = 3, stride: int = 1,
                 indice_key: str | None = None) -> SparseSequential:
    """Submanifold conv (stride 1) or strided sparse conv, then BN and ReLU."""
    if stride == 1:
        conv = layers.SubMConv3d(cin, cout, kernel, indice_key=indice_key)
    else:
        conv = layers.SparseConv3d(cin, cout, kernel, stride, indice_key=indice_key)
    return SparseSequential(conv, SparseBatchNorm(cout), SparseReLU())


def deconv_bn_relu(layers: SimpleNamespace, cin: int, cout: int, kernel: int, indice_key: str) -> SparseSequential:
    """Inverse conv back to the level of the strided conv ``indice_key``, BN, ReLU."""
    return SparseSequential(layers.SparseInverseConv3d(cin, cout, kernel, indice_key=indice_key),
                            SparseBatchNorm(cout), SparseReLU())


class ResidualBlock(nn.Module):
    """Basic block: conv3-BN-ReLU-conv3-BN plus shortcut (1x1x1 conv-BN if widths differ), ReLU."""

    def __init__(self, layers: SimpleNamespace, cin: int, cout: int, indice_key: str):
        super().__init__()
        self.body = SparseSequential(
            layers.SubMConv3d(cin, cout, 3, indice_key=indice_key), SparseBatchNorm(cout), SparseReLU(),
            layers.SubMConv3d(cout, cout, 3, indice_key=indice_key), SparseBatchNorm(cout),
        )
        self.shortcut = None
        if cin != cout:
            self.shortcut = SparseSequential(layers.SubMConv3d(cin, cout, 1), SparseBatchNorm(cout))
        self.relu = nn.ReLU()

    def forward(self, x: SparseTensor) -> SparseTensor:
        y = self.body(x)
        skip = x.feats if self.shortcut is None else self.shortcut(x).feats
        return y.replace_feats(self.relu(y.feats + skip))


def residual_stage(layers, cin: int, cout: int, blocks: int, indice_key: str) -> SparseSequential:
    mods = [ResidualBlock(layers, cin if i == 0 else cout, cout, indice_key) for i in range(blocks)]
    return SparseSequential(*mods)


def concat(a: SparseTensor, b: SparseTensor) -> SparseTensor:
    """Channel concatenation of two tensors on the same coordinates."""
    if a.num_voxels != b.num_voxels:
        raise ValueError(f"cannot concatenate tensors with {a.num_voxels} and {b.num_voxels} voxels")
    return a.replace_feats(torch.cat([a.feats, b.feats], 1))


LEVELS = 4  # stride-2 stages: the bottom level has stride 16


def network_input(batch: SegBatch) -> SparseTensor:
    """The batch's voxels with the grid padded to a multiple of 2**LEVELS.

    A kernel-2 stride-2 convolution follows conv3d's output size, which drops
    the last cell of an odd-sized axis; padding keeps every voxel alive at
    every level.
    """
    x = batch.sparse_input()
    m = 2**LEVELS
    x.spatial_shape = tuple(-(-s // m) * m for s in x.spatial_shape)
    return x


def init_weights(model: nn.Module, generator: torch.Generator | None) -> None:
    """Re-initialise every parameter from ``generator`` (reproducible init).

    Sparse convs: uniform +-1/sqrt(fan_in); Linear: the same; BatchNorm: 1, 0.
    """
    for m in model.modules():
        if hasattr(m, "reset_parameters") and hasattr(m, "indice_key"):
            m.reset_parameters(generator)
        elif isinstance(m, nn.Linear):
            bound = 1.0 / m.in_features ** 0.5
            with torch.no_grad():
                nn.init.uniform_(m.weight, -bound, bound, generator=generator)
                if m.bias is not None:
                    nn.init.uniform_(m.bias, -bound, bound, generator=generator)
        elif isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.reset_parameters()


class UNetTrunk(nn.Module):
    """Stem, encoder and decoder stages shared by MinkUNet and SPVCNN."""

    def __init__(self, in_channels: int, width: str, depth: int, backend: str, device):
        super().__init__()
        if width not in WIDTHS:
            raise ValueError(f"width must be one of {sorted(WIDTHS)}, got {width!r}")
        if depth not in ENCODER_BLOCKS:
            raise ValueError(f"depth must be one of {sorted(ENCODER_BLOCKS)}, got {depth}")
        layers = conv_layers(backend, device)
        self.backend = layers.name
        stem, enc, dec = WIDTHS[width]
        self.stem_channels, self.encoder_channels, self.decoder_channels = stem, enc, dec
        self.stem = SparseSequential(
            conv_bn_relu(layers, in_channels, stem, 3, indice_key="subm1"),
            conv_bn_relu(layers, stem, stem, 3, indice_key="subm1"),
        )
        self.encoder = nn.ModuleList()
        cin = stem
        for i, (cout, blocks) in enumerate(zip(enc, ENCODER_BLOCKS[depth])):
            self.encoder.append(SparseSequential(
                conv_bn_relu(layers, cin, cin, 2, 2, indice_key=f"down{i + 1}"),
                residual_stage(layers, cin, cout, blocks, f"subm{2 ** (i + 1)}"),
            ))
            cin = cout
        skips = (enc[2], enc[1], enc[0], stem)
        self.up = nn.ModuleList()
        self.fuse = nn.ModuleList()
        for i, (cout, skip, blocks) in enumerate(zip(dec, skips, DECODER_BLOCKS)):
            level = 4 - i  # the up conv inverts down{level}
            self.up.append(deconv_bn_relu(layers, cin, cout, 2, indice_key=f"down{level}"))
            self.fuse.append(residual_stage(layers, cout + skip, cout, blocks, f"subm{2 ** (level - 1)}"))
            cin = cout


class MinkUNet(nn.Module):
    """Sparse voxel U-Net; ``forward(batch)`` returns per-point logits ``(P, 19)``."""

    def __init__(self, in_channels: int = 4, num_classes: int = NUM_SEG_CLASSES, width: str = "W32",
                 depth: int = 18, backend: str = "auto", device: str | torch.device = "cpu",
                 generator: torch.Generator | None = None):
        super().__init__()
        self.trunk = UNetTrunk(in_channels, width, depth, backend, device)
        self.classifier = nn.Linear(self.trunk.decoder_channels[-1], num_classes)
        init_weights(self, generator)

    @property
    def backend(self) -> str:
        return self.trunk.backend

    def voxel_logits(self, batch: SegBatch) -> torch.Tensor:
        """Logits of every voxel of the batch, ``(M, classes)``."""
        t = self.trunk
        x = t.stem(network_input(batch))
        skips = [x]
        for stage in t.encoder:
            x = stage(x)
            skips.append(x)
        for i, (up, fuse) in enumerate(zip(t.up, t.fuse)):
            x = fuse(concat(up(x), skips[3 - i]))
        return self.classifier(x.feats)

    def forward(self, batch: SegBatch) -> torch.Tensor:
        """Per-point logits ``(P, classes)``: each point takes its voxel's."""
        return self.voxel_logits(batch)[batch.point_to_voxel]


def minkunet(variant: str = "W32", **kwargs) -> MinkUNet:
    """Build a named variant: ``W16``, ``W20``, ``W32`` (depth 18) or ``MinkUNet34`` (W32 widths)."""
    if variant == "MinkUNet34":
        return MinkUNet(width="W32", depth=34, **kwargs)
    return MinkUNet(width=variant, depth=18, **kwargs)
