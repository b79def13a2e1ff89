"""A sparse 3D feature map: active voxel coordinates plus one feature row each.

Coordinates are int32 ``(N, 4)`` rows ``batch, x, y, z`` in voxel units of the
tensor's own level: a stride-2 convolution maps ``x`` to ``x // 2`` (the spconv
convention), so every level lives on a grid ``[0, spatial_shape)``.

``cache`` is a dict shared by every tensor derived from one input (convolutions
pass it on). Kernel maps are stored there under the convolutions'
``indice_key`` so that later layers reuse them: submanifold layers on the same
coordinates, and inverse convolutions that undo a strided one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class SparseTensor:
    """Sparse voxel features.

    feats: ``(N, C)`` floating point features.
    coords: ``(N, 4)`` int32 ``batch, x, y, z``, unique rows, each axis in
        ``[0, spatial_shape[axis])`` and batch in ``[0, batch_size)``.
    spatial_shape: grid size ``(X, Y, Z)`` of this level.
    batch_size: number of samples in the batch.
    cache: kernel maps keyed by ``indice_key``, shared along the network.
    """

    feats: torch.Tensor
    coords: torch.Tensor
    spatial_shape: tuple[int, int, int]
    batch_size: int
    cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self.spatial_shape = tuple(int(s) for s in self.spatial_shape)
        if len(self.spatial_shape) != 3 or min(self.spatial_shape) < 1:
            raise ValueError(f"spatial_shape must be 3 positive ints, got {self.spatial_shape}")
        if self.coords.dtype != torch.int32 or self.coords.dim() != 2 or self.coords.shape[1] != 4:
            raise ValueError(
                f"coords must be int32 (N, 4) batch,x,y,z; got {self.coords.dtype} {tuple(self.coords.shape)}"
            )
        if self.feats.dim() != 2 or self.feats.shape[0] != self.coords.shape[0]:
            raise ValueError(
                f"feats must be (N, C) with N = {self.coords.shape[0]} rows; got {tuple(self.feats.shape)}"
            )
        if not self.feats.is_floating_point():
            raise ValueError(f"feats must be floating point, got {self.feats.dtype}")

    @property
    def num_voxels(self) -> int:
        return int(self.coords.shape[0])

    @property
    def device(self) -> torch.device:
        return self.feats.device

    def replace_feats(self, feats: torch.Tensor) -> "SparseTensor":
        """The same coordinates (and shared cache) with new features."""
        return SparseTensor(feats, self.coords, self.spatial_shape, self.batch_size, self.cache)

    def validate(self) -> None:
        """Check value ranges and uniqueness (O(N log N)); raises ValueError."""
        c = self.coords.long()
        if c.numel():
            lo = c.min(0).values
            hi = c.max(0).values
            if lo.min() < 0:
                raise ValueError("coords contain negative values")
            if hi[0] >= self.batch_size:
                raise ValueError(f"batch index {int(hi[0])} >= batch_size {self.batch_size}")
            for axis in range(3):
                if hi[axis + 1] >= self.spatial_shape[axis]:
                    raise ValueError(
                        f"coordinate {int(hi[axis + 1])} on axis {axis} outside spatial_shape {self.spatial_shape}"
                    )
            keys = pack_coords(self.coords, self.spatial_shape)
            if torch.unique(keys).numel() != keys.numel():
                raise ValueError("coords contain duplicate rows")
        if not torch.isfinite(self.feats).all():
            raise ValueError("feats contain NaN or Inf")

    def dense(self) -> torch.Tensor:
        """Scatter into a dense ``(B, C, X, Y, Z)`` tensor (zeros elsewhere)."""
        out = self.feats.new_zeros((self.batch_size, *self.spatial_shape, self.feats.shape[1]))
        c = self.coords.long()
        out[c[:, 0], c[:, 1], c[:, 2], c[:, 3]] = self.feats
        return out.permute(0, 4, 1, 2, 3).contiguous()

    def to(self, device) -> "SparseTensor":
        return SparseTensor(
            self.feats.to(device), self.coords.to(device), self.spatial_shape, self.batch_size, {}
        )


def pack_coords(coords: torch.Tensor, spatial_shape) -> torch.Tensor:
    """Pack ``(N, 4)`` batch,x,y,z rows into unique int64 keys (row-major order).

    Keys sort batch-major, then x, y, z, so sorting keys sorts voxels.
    Rows must lie inside ``spatial_shape``; callers mask out-of-range rows first.
    """
    sx, sy, sz = (int(s) for s in spatial_shape)
    c = coords.long()
    return ((c[:, 0] * sx + c[:, 1]) * sy + c[:, 2]) * sz + c[:, 3]


def unpack_keys(keys: torch.Tensor, spatial_shape) -> torch.Tensor:
    """Inverse of :func:`pack_coords`: int64 keys -> int32 ``(N, 4)`` rows."""
    sx, sy, sz = (int(s) for s in spatial_shape)
    z = keys % sz
    rest = keys // sz
    y = rest % sy
    rest = rest // sy
    x = rest % sx
    b = rest // sx
    return torch.stack([b, x, y, z], dim=1).to(torch.int32)
