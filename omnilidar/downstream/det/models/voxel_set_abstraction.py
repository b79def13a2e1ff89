"""PV-RCNN's voxel set abstraction (the PFE stage): keypoints summarise the scene.

Per sample, farthest point sampling picks ``NUM_KEYPOINTS`` keypoints from the raw
points (or voxel centres). Each keypoint then gathers features from every source
in ``FEATURES_SOURCE``:

- ``bev``: bilinear interpolation of the height-compressed BEV map
  (``spatial_features`` at ``spatial_features_stride``);
- ``raw_points``: a StackSAModuleMSG over the raw points' extra channels;
- ``x_conv1`` .. ``x_conv4``: a StackSAModuleMSG over the sparse backbone's voxel
  centres at ``DOWNSAMPLE_FACTOR``.

The concatenation is ``point_features_before_fusion``; a Linear-BN-ReLU
(``vsa_point_feature_fusion``) maps it to ``NUM_OUTPUT_FEATURES``. Names follow
OpenPCDet (``SA_layers``, ``SA_rawpoints``, ``vsa_point_feature_fusion``).

One deliberate difference: OpenPCDet computes the bilinear weights from the
clamped corner indices, so a keypoint in the last half cell of the BEV map gets
weights summing to zero; here the weights come from the unclamped corners and
the clamped corners only choose which cells to read (edge replication).
Everywhere inside the map both give the same value.
"""

from __future__ import annotations

import torch
from torch import nn

from omnilidar.downstream.det.models.box_utils import voxel_centers
from omnilidar.downstream.det.models.pointnet2_stack import (
    batch_counts,
    build_local_aggregation_module,
    sort_by_batch,
)
from omnilidar.downstream.det.ops.sampling import farthest_point_sample

VOXEL_SOURCES = ("x_conv1", "x_conv2", "x_conv3", "x_conv4")


def sparse_coords_and_features(tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(N, 4)`` [batch, z, y, x] indices and ``(N, C)`` features of a sparse map.

    Accepts spconv's SparseConvTensor (``indices``, ``features``) and our
    :class:`omnilidar.sparse.tensor.SparseTensor` (``coords``, ``feats``), which the
    detection backbone builds on a (Z, Y, X) grid, so its rows are batch, z, y, x too.
    """
    if hasattr(tensor, "indices") and hasattr(tensor, "features"):
        return tensor.indices, tensor.features
    if hasattr(tensor, "coords") and hasattr(tensor, "feats"):
        return tensor.coords, tensor.feats
    raise TypeError(f"not a sparse feature map: {type(tensor).__name__}")


def bilinear_interpolate(image: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Sample an ``(H, W, C)`` map at fractional pixel positions ``x`` (column), ``y`` (row)."""
    h, w = image.shape[0], image.shape[1]
    x0f, y0f = torch.floor(x), torch.floor(y)
    wx1, wy1 = x - x0f, y - y0f
    wx0, wy0 = 1.0 - wx1, 1.0 - wy1
    x0 = x0f.long().clamp(0, w - 1)
    x1 = (x0f.long() + 1).clamp(0, w - 1)
    y0 = y0f.long().clamp(0, h - 1)
    y1 = (y0f.long() + 1).clamp(0, h - 1)
    return (
        image[y0, x0] * (wx0 * wy0)[:, None]
        + image[y1, x0] * (wx0 * wy1)[:, None]
        + image[y0, x1] * (wx1 * wy0)[:, None]
        + image[y1, x1] * (wx1 * wy1)[:, None]
    )


class VoxelSetAbstraction(nn.Module):
    def __init__(self, model_cfg: dict, voxel_size, point_cloud_range, num_bev_features=None,
                 num_rawpoint_features=None, backbone_channels: dict | None = None, **kwargs):
        super().__init__()
        self.model_cfg = model_cfg
        self.voxel_size = [float(v) for v in voxel_size]
        self.point_cloud_range = [float(v) for v in point_cloud_range]
        self.num_keypoints = int(model_cfg["NUM_KEYPOINTS"])
        self.point_source = model_cfg.get("POINT_SOURCE", "raw_points")
        self.sources = list(model_cfg["FEATURES_SOURCE"])
        if model_cfg.get("SAMPLE_METHOD", "FPS") != "FPS":
            raise ValueError(f"PFE SAMPLE_METHOD {model_cfg.get('SAMPLE_METHOD')!r} is not supported (only FPS)")
        if self.point_source not in ("raw_points", "voxel_centers"):
            raise ValueError(f"PFE POINT_SOURCE must be raw_points or voxel_centers, got {self.point_source!r}")
        unknown = [s for s in self.sources if s not in ("bev", "raw_points", *VOXEL_SOURCES)]
        if unknown:
            raise ValueError(f"PFE FEATURES_SOURCE has unknown sources {unknown}")
        sa_cfg = model_cfg["SA_LAYER"]
        for name in self.sources:
            if name != "bev" and sa_cfg.get(name, {}).get("FILTER_NEIGHBOR_WITH_ROI", False):
                raise ValueError(f"PFE SA_LAYER.{name}.FILTER_NEIGHBOR_WITH_ROI is not supported")

        self.SA_layers = nn.ModuleList()
        self.SA_layer_names: list[str] = []
        self.downsample_times_map: dict[str, int] = {}
        self.sa_input_channels: dict[str, int] = {}
        c_in = 0
        for name in self.sources:
            if name in ("bev", "raw_points"):
                continue
            layer_cfg = sa_cfg[name]
            self.downsample_times_map[name] = int(layer_cfg["DOWNSAMPLE_FACTOR"])
            # The input width: INPUT_CHANNELS, else the backbone's width at that level, else
            # (OpenPCDet's rule, the same for its published configs) the first MLP width.
            channels = layer_cfg.get("INPUT_CHANNELS")
            known = (backbone_channels or {}).get(name)
            if channels is None:
                channels = known
            elif known is not None and int(channels) != int(known):
                raise ValueError(f"PFE.SA_LAYER.{name}.INPUT_CHANNELS is {channels} but the 3D backbone's "
                                 f"{name} has {known} channels")
            if channels is None:
                first = layer_cfg["MLPS"][0]
                channels = first[0] if isinstance(first, (list, tuple)) else first
            self.sa_input_channels[name] = int(channels)
            layer, c_out = build_local_aggregation_module(int(channels), layer_cfg)
            self.SA_layers.append(layer)
            self.SA_layer_names.append(name)
            c_in += c_out
        if "bev" in self.sources:
            if num_bev_features is None:
                raise ValueError("PFE uses 'bev' features but num_bev_features is unknown")
            c_in += int(num_bev_features)
        if "raw_points" in self.sources:
            if num_rawpoint_features is None:
                raise ValueError("PFE uses 'raw_points' features but num_rawpoint_features is unknown")
            self.SA_rawpoints, c_out = build_local_aggregation_module(
                int(num_rawpoint_features) - 3, sa_cfg["raw_points"]
            )
            c_in += c_out

        c_out = int(model_cfg["NUM_OUTPUT_FEATURES"])
        self.vsa_point_feature_fusion = nn.Sequential(
            nn.Linear(c_in, c_out, bias=False), nn.BatchNorm1d(c_out), nn.ReLU()
        )
        self.num_point_features = c_out
        self.num_point_features_before_fusion = c_in

    def sample_keypoints(self, batch_dict: dict) -> torch.Tensor:
        """``(B * NUM_KEYPOINTS, 4)`` [batch, x, y, z] keypoints by farthest point sampling.

        A sample with fewer points than keypoints repeats its sampled points
        cyclically, as OpenPCDet does.
        """
        batch_size = int(batch_dict["batch_size"])
        if self.point_source == "raw_points":
            src = batch_dict["points"][:, 1:4]
            batch_idx = batch_dict["points"][:, 0].long()
        else:
            coords = batch_dict["voxel_coords"]
            src = voxel_centers(coords[:, 1:4], 1, self.voxel_size, self.point_cloud_range)
            batch_idx = coords[:, 0].long()
        keypoints = []
        for b in range(batch_size):
            pts = src[batch_idx == b]
            n = pts.shape[0]
            if n == 0:
                raise ValueError(f"sample {b} of the batch has no points to pick keypoints from")
            idx = farthest_point_sample(pts[None].contiguous(), min(n, self.num_keypoints))[0].long()
            if n < self.num_keypoints:
                idx = idx.repeat(self.num_keypoints // n + 1)[: self.num_keypoints]
            kp = pts[idx]
            keypoints.append(torch.cat([kp.new_full((kp.shape[0], 1), float(b)), kp], dim=1))
        return torch.cat(keypoints, dim=0)

    def interpolate_from_bev_features(self, keypoints, bev_features, batch_size, bev_stride):
        """BEV features ``(B, C, H, W)`` at the keypoints -> ``(num_keypoints, C)``."""
        x = (keypoints[:, 1] - self.point_cloud_range[0]) / self.voxel_size[0] / bev_stride
        y = (keypoints[:, 2] - self.point_cloud_range[1]) / self.voxel_size[1] / bev_stride
        out = []
        for b in range(batch_size):
            mask = keypoints[:, 0] == b
            out.append(bilinear_interpolate(bev_features[b].permute(1, 2, 0), x[mask], y[mask]))
        return torch.cat(out, dim=0)

    def aggregate(self, layer, batch_size, xyz, features, batch_idx, new_xyz, new_xyz_batch_cnt):
        batch_idx, xyz, features = sort_by_batch(batch_idx, xyz, features)
        xyz_batch_cnt = batch_counts(batch_idx, batch_size)
        _, pooled = layer(
            xyz=xyz.contiguous(), xyz_batch_cnt=xyz_batch_cnt, new_xyz=new_xyz,
            new_xyz_batch_cnt=new_xyz_batch_cnt,
            features=None if features is None else features.contiguous(),
        )
        return pooled

    def forward(self, batch_dict: dict) -> dict:
        """Adds ``point_features`` (K, C), ``point_features_before_fusion`` and
        ``point_coords`` (K, 4) [batch, x, y, z] to ``batch_dict``."""
        batch_size = int(batch_dict["batch_size"])
        keypoints = self.sample_keypoints(batch_dict)
        new_xyz = keypoints[:, 1:4].contiguous()
        new_xyz_batch_cnt = batch_counts(keypoints[:, 0], batch_size)

        features = []
        if "bev" in self.sources:
            features.append(self.interpolate_from_bev_features(
                keypoints, batch_dict["spatial_features"], batch_size, batch_dict["spatial_features_stride"]
            ))
        if "raw_points" in self.sources:
            points = batch_dict["points"]
            extra = points[:, 4:] if points.shape[1] > 4 else None
            features.append(self.aggregate(
                self.SA_rawpoints, batch_size, points[:, 1:4], extra, points[:, 0], new_xyz, new_xyz_batch_cnt
            ))
        for layer, name in zip(self.SA_layers, self.SA_layer_names):
            coords, feats = sparse_coords_and_features(batch_dict["multi_scale_3d_features"][name])
            if feats.shape[1] != self.sa_input_channels[name]:
                raise ValueError(
                    f"PFE SA_LAYER.{name} expects {self.sa_input_channels[name]} input channels "
                    f"but the backbone gives {feats.shape[1]} (set INPUT_CHANNELS or MLPS)"
                )
            xyz = voxel_centers(coords[:, 1:4], self.downsample_times_map[name], self.voxel_size,
                                self.point_cloud_range)
            features.append(self.aggregate(layer, batch_size, xyz, feats, coords[:, 0], new_xyz, new_xyz_batch_cnt))

        before_fusion = torch.cat(features, dim=1)
        batch_dict["point_features_before_fusion"] = before_fusion
        batch_dict["point_features"] = self.vsa_point_feature_fusion(before_fusion)
        batch_dict["point_coords"] = keypoints
        return batch_dict
