"""VoxelRCNNHead (OpenPCDet roi_heads.voxelrcnn_head): a GRID_SIZE^3 grid of
points in each RoI pools the 3D backbone's voxels at several strides (voxel
query + NeighborVoxelSAModuleMSG); shared, class and box FC layers refine."""

from __future__ import annotations

import copy

import torch
from torch import nn

from omnilidar.downstream.det.models.box_utils import rotate_points_along_z, voxel_centers
from omnilidar.downstream.det.models.roi_head_template import RoIHeadTemplate
from omnilidar.downstream.det.models.voxel_pool import NeighborVoxelSAModuleMSG
from omnilidar.downstream.det.ops.sampling import VoxelMap


def _fc_stack(pre_channel: int, widths, dp_ratio: float, inplace: bool = False):
    layers = []
    for k, width in enumerate(widths):
        layers += [nn.Linear(pre_channel, width, bias=False), nn.BatchNorm1d(width), nn.ReLU(inplace=inplace)]
        pre_channel = width
        if k != len(widths) - 1 and dp_ratio > 0:
            layers.append(nn.Dropout(dp_ratio))
    return nn.Sequential(*layers), pre_channel


class VoxelRCNNHead(RoIHeadTemplate):
    def __init__(self, backbone_channels: dict, model_cfg: dict, point_cloud_range, voxel_size,
                 num_class: int = 1, generator: torch.Generator | None = None, **_):
        super().__init__(num_class=num_class, model_cfg=model_cfg, generator=generator)
        self.pool_cfg = model_cfg["ROI_GRID_POOL"]
        self.point_cloud_range = [float(v) for v in point_cloud_range]
        self.voxel_size = [float(v) for v in voxel_size]
        self.roi_grid_pool_layers = nn.ModuleList()
        c_out = 0
        for src in self.pool_cfg["FEATURES_SOURCE"]:
            layer_cfg = self.pool_cfg["POOL_LAYERS"][src]
            mlps = [[backbone_channels[src], *m] for m in copy.deepcopy(layer_cfg["MLPS"])]
            self.roi_grid_pool_layers.append(NeighborVoxelSAModuleMSG(
                query_ranges=layer_cfg["QUERY_RANGES"], radii=layer_cfg["POOL_RADIUS"],
                nsamples=layer_cfg["NSAMPLE"], mlps=mlps, pool_method=layer_cfg.get("POOL_METHOD", "max_pool")))
            c_out += sum(m[-1] for m in mlps)
        grid = int(self.pool_cfg["GRID_SIZE"])
        dp = float(model_cfg.get("DP_RATIO", 0.0))
        self.shared_fc_layer, pre = _fc_stack(grid ** 3 * c_out, model_cfg["SHARED_FC"], dp, inplace=True)
        self.cls_fc_layers, cls_pre = _fc_stack(pre, model_cfg["CLS_FC"], dp)
        self.cls_pred_layer = nn.Linear(cls_pre, self.num_class, bias=True)
        self.reg_fc_layers, reg_pre = _fc_stack(pre, model_cfg["REG_FC"], dp)
        self.reg_pred_layer = nn.Linear(reg_pre, self.box_coder.code_size * self.num_class, bias=True)
        self._init_weights()

    def _init_weights(self) -> None:
        for stack in (self.shared_fc_layer, self.cls_fc_layers, self.reg_fc_layers):
            for m in stack.modules():
                if isinstance(m, nn.Linear):
                    nn.init.xavier_normal_(m.weight)
                    if m.bias is not None:
                        nn.init.constant_(m.bias, 0)
        nn.init.normal_(self.cls_pred_layer.weight, 0, 0.01)
        nn.init.constant_(self.cls_pred_layer.bias, 0)
        nn.init.normal_(self.reg_pred_layer.weight, mean=0, std=0.001)
        nn.init.constant_(self.reg_pred_layer.bias, 0)

    @staticmethod
    def grid_points_of_rois(rois: torch.Tensor, grid_size: int) -> torch.Tensor:
        """(R, G^3, 3) lidar-frame centres of each RoI's G x G x G cells (x slowest)."""
        rois = rois.view(-1, rois.shape[-1])
        idx = torch.stack(torch.meshgrid(*[torch.arange(grid_size, device=rois.device)] * 3, indexing="ij"), -1)
        idx = idx.view(1, -1, 3).to(rois.dtype)
        size = rois[:, None, 3:6]
        local = (idx + 0.5) / grid_size * size - size / 2
        return rotate_points_along_z(local, rois[:, 6]) + rois[:, None, 0:3]

    def roi_grid_pool(self, batch_dict: dict) -> torch.Tensor:
        rois = batch_dict["rois"]
        batch_size = int(batch_dict["batch_size"])
        grid = int(self.pool_cfg["GRID_SIZE"])
        grid_xyz = self.grid_points_of_rois(rois, grid).view(batch_size, -1, 3)
        origin = grid_xyz.new_tensor(self.point_cloud_range[0:3])
        vsize = grid_xyz.new_tensor(self.voxel_size)
        grid_coords = torch.div(grid_xyz - origin, vsize, rounding_mode="floor")  # x, y, z voxel units
        batch_idx = torch.arange(batch_size, device=rois.device, dtype=grid_xyz.dtype)
        batch_idx = batch_idx[:, None, None].expand(batch_size, grid_coords.shape[1], 1)
        grid_cnt = torch.full((batch_size,), grid_coords.shape[1], dtype=torch.int32, device=rois.device)
        pooled = []
        for layer, src in zip(self.roi_grid_pool_layers, self.pool_cfg["FEATURES_SOURCE"]):
            stride = batch_dict["multi_scale_3d_strides"][src]
            sp = batch_dict["multi_scale_3d_features"][src]
            coords = sp.coords.long()
            xyz = voxel_centers(coords[:, 1:4], stride, self.voxel_size, self.point_cloud_range)
            xyz_cnt = torch.bincount(coords[:, 0], minlength=batch_size).int()
            scale_coords = torch.cat([batch_idx, torch.div(grid_coords, stride, rounding_mode="floor")], -1).int()
            features = layer(xyz=xyz, xyz_batch_cnt=xyz_cnt, new_xyz=grid_xyz.reshape(-1, 3),
                             new_xyz_batch_cnt=grid_cnt, new_coords=scale_coords.view(-1, 4),
                             features=sp.feats,
                             voxel2point_indices=VoxelMap.from_coords(sp.coords, (batch_size, *sp.spatial_shape)))
            pooled.append(features.view(-1, grid ** 3, features.shape[-1]))
        return torch.cat(pooled, dim=-1)

    def forward(self, batch_dict: dict) -> dict:
        nms_cfg = self.model_cfg["NMS_CONFIG"]["TRAIN" if self.training else "TEST"]
        self.proposal_layer(batch_dict, nms_cfg)
        if self.training:
            targets = self.assign_targets(batch_dict)
            batch_dict["rois"] = targets["rois"]
            batch_dict["roi_labels"] = targets["roi_labels"]
        pooled = self.roi_grid_pool(batch_dict)
        shared = self.shared_fc_layer(pooled.reshape(pooled.shape[0], -1))
        rcnn_cls = self.cls_pred_layer(self.cls_fc_layers(shared))
        rcnn_reg = self.reg_pred_layer(self.reg_fc_layers(shared))
        if self.training:
            targets["rcnn_cls"] = rcnn_cls
            targets["rcnn_reg"] = rcnn_reg
            self.forward_ret_dict = targets
        else:
            cls, boxes = self.generate_predicted_boxes(int(batch_dict["batch_size"]), batch_dict["rois"],
                                                       rcnn_cls, rcnn_reg)
            batch_dict["batch_cls_preds"] = cls
            batch_dict["batch_box_preds"] = boxes
            batch_dict["cls_preds_normalized"] = False
        return batch_dict
