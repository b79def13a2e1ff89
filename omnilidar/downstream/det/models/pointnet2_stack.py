"""PointNet++ set abstraction on stacked batches (OpenPCDet's ``pointnet2_stack``).

A "stacked" batch concatenates the points of every sample in batch order and
carries a count per sample (``xyz_batch_cnt``) instead of padding to (B, N).
:class:`StackSAModuleMSG` groups, for every query centre, the neighbours found by
a ball query at several radii, runs a shared 1x1-conv MLP on
``[relative xyz, features]`` and max-pools over the neighbours. Module and
parameter names (``groupers``, ``mlps.<scale>.<layer>``) follow OpenPCDet so that
its checkpoints load strictly.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from omnilidar.downstream.det.ops.sampling import QueryAndGroup


def shared_mlp(channels: list[int]) -> nn.Sequential:
    """1x1 Conv2d (no bias) - BatchNorm2d - ReLU per step, OpenPCDet's layer order."""
    layers: list[nn.Module] = []
    for c_in, c_out in zip(channels[:-1], channels[1:]):
        layers += [nn.Conv2d(c_in, c_out, kernel_size=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU()]
    return nn.Sequential(*layers)


class StackSAModuleMSG(nn.Module):
    """Multi-scale grouping set abstraction on stacked batches.

    ``mlps[k]`` lists the channels of scale ``k`` starting with the input feature
    width (3 is added for the relative xyz when ``use_xyz``).
    """

    def __init__(self, *, radii, nsamples, mlps, use_xyz: bool = True, pool_method: str = "max_pool"):
        super().__init__()
        if not len(radii) == len(nsamples) == len(mlps):
            raise ValueError(f"radii, nsamples and mlps differ in length: {len(radii)}, {len(nsamples)}, {len(mlps)}")
        if pool_method not in ("max_pool", "avg_pool"):
            raise ValueError(f"pool_method must be max_pool or avg_pool, got {pool_method!r}")
        self.groupers = nn.ModuleList(QueryAndGroup(r, n, use_xyz=use_xyz) for r, n in zip(radii, nsamples))
        self.mlps = nn.ModuleList(
            shared_mlp([spec[0] + (3 if use_xyz else 0), *spec[1:]]) for spec in mlps
        )
        self.pool_method = pool_method
        self.num_output_features = sum(spec[-1] for spec in mlps)
        self.init_weights()

    def init_weights(self):
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt, features=None):
        """Returns ``(new_xyz, (M, sum of the scales' last widths))``."""
        pooled = []
        for grouper, mlp in zip(self.groupers, self.mlps):
            grouped, _ = grouper(xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt, features)  # (M, C, ns)
            m, c, ns = grouped.shape
            x = run_shared_mlp(mlp, grouped.transpose(1, 2).reshape(m * ns, c)).view(m, ns, -1)
            pooled.append(x.amax(dim=1) if self.pool_method == "max_pool" else x.mean(dim=1))
        return new_xyz, torch.cat(pooled, dim=1)


def run_shared_mlp(mlp: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """Apply a :func:`shared_mlp` to rows ``(N, C)``: the same result as the 1x1 Conv2d
    stack on ``(1, C, N, 1)``, as matrix products (several times faster backward on CPU)."""
    for layer in mlp:
        if isinstance(layer, nn.Conv2d):
            x = F.linear(x, layer.weight.flatten(1), layer.bias)
        elif isinstance(layer, nn.BatchNorm2d):
            x = layer(x[:, :, None, None]).view(x.shape)
        else:
            x = layer(x)
    return x


def build_local_aggregation_module(input_channels: int, config: dict) -> tuple[StackSAModuleMSG, int]:
    """A StackSAModuleMSG from an OpenPCDet SA_LAYER / ROI_GRID_POOL section.

    ``config`` holds MLPS, POOL_RADIUS and NSAMPLE; the input width is prepended to
    every MLPS entry (without mutating ``config``, unlike OpenPCDet).
    """
    name = config.get("NAME", "StackSAModuleMSG")
    if name != "StackSAModuleMSG":
        raise ValueError(f"local aggregation {name!r} is not supported (only StackSAModuleMSG)")
    mlps = [[int(input_channels), *spec] for spec in config["MLPS"]]
    module = StackSAModuleMSG(
        radii=config["POOL_RADIUS"], nsamples=config["NSAMPLE"], mlps=mlps, use_xyz=True,
        pool_method=config.get("POOL_METHOD", "max_pool"),
    )
    return module, module.num_output_features


def batch_counts(batch_idx: torch.Tensor, batch_size: int) -> torch.Tensor:
    """Rows per sample as int32 ``(batch_size,)``; rows must already be in batch order."""
    return torch.bincount(batch_idx.long(), minlength=batch_size)[:batch_size].int()


def sort_by_batch(batch_idx: torch.Tensor, *tensors: torch.Tensor):
    """Reorder rows so samples are contiguous (a stable sort; no-op when sorted)."""
    b = batch_idx.long()
    if b.numel() < 2 or bool((b[1:] >= b[:-1]).all()):
        return (batch_idx, *tensors)
    order = torch.argsort(b, stable=True)
    return (batch_idx[order], *(t[order] if t is not None else None for t in tensors))
