"""PV-RCNN's second stage (OpenPCDet's PVRCNNHead): RoI-grid pooling of keypoints.

Every RoI gets a ``GRID_SIZE``^3 grid of points (cell centres in the box frame,
rotated by the heading and moved to the box centre). A StackSAModuleMSG
(``roi_grid_pool_layer``) pools the keypoint features, each weighted by its
foreground score from the point head, around every grid point. The pooled
``(RoIs, C, G, G, G)`` volume is flattened channel-major and goes through
``shared_fc_layer`` (1x1 Conv1d-BN-ReLU, dropout between layers), then
``cls_layers`` (confidence, one logit per class or one when class-agnostic) and
``reg_layers`` (box residuals w.r.t. the RoI). Proposal NMS, target sampling,
losses and box decoding come from the shared :class:`RoIHeadTemplate`; the grid
points are Voxel R-CNN's (:meth:`VoxelRCNNHead.grid_points_of_rois`).
"""

from __future__ import annotations

import torch
from torch import nn

from omnilidar.downstream.det.models.pointnet2_stack import batch_counts, build_local_aggregation_module
from omnilidar.downstream.det.models.roi_head_template import RoIHeadTemplate
from omnilidar.downstream.det.models.voxel_rcnn_head import VoxelRCNNHead


def make_fc_layers(input_channels: int, output_channels: int, fc_list, dp_ratio: float) -> nn.Sequential:
    """OpenPCDet's RoIHeadTemplate.make_fc_layers: 1x1 Conv1d-BN-ReLU per width, a Dropout
    after the first (whenever DP_RATIO >= 0, so layer indices do not depend on it), then
    a 1x1 Conv1d with bias to the outputs."""
    layers: list[nn.Module] = []
    pre = int(input_channels)
    for k, c in enumerate(fc_list):
        layers += [nn.Conv1d(pre, c, kernel_size=1, bias=False), nn.BatchNorm1d(c), nn.ReLU()]
        pre = c
        if dp_ratio >= 0 and k == 0:
            layers.append(nn.Dropout(dp_ratio))
    layers.append(nn.Conv1d(pre, output_channels, kernel_size=1, bias=True))
    return nn.Sequential(*layers)


class PVRCNNHead(RoIHeadTemplate):
    def __init__(self, input_channels: int, model_cfg: dict, num_class: int = 1,
                 generator: torch.Generator | None = None, **kwargs):
        super().__init__(num_class=num_class, model_cfg=model_cfg, generator=generator)
        pool_cfg = model_cfg["ROI_GRID_POOL"]
        self.grid_size = int(pool_cfg["GRID_SIZE"])
        self.roi_grid_pool_layer, c_pooled = build_local_aggregation_module(int(input_channels), pool_cfg)

        pre_channel = self.grid_size ** 3 * c_pooled
        shared: list[nn.Module] = []
        fcs = list(model_cfg["SHARED_FC"])
        dp_ratio = float(model_cfg.get("DP_RATIO", 0.0))
        for k, c in enumerate(fcs):
            shared += [nn.Conv1d(pre_channel, c, kernel_size=1, bias=False), nn.BatchNorm1d(c), nn.ReLU()]
            pre_channel = c
            if k != len(fcs) - 1 and dp_ratio > 0:
                shared.append(nn.Dropout(dp_ratio))
        self.shared_fc_layer = nn.Sequential(*shared)
        self.cls_layers = make_fc_layers(pre_channel, self.num_class, model_cfg["CLS_FC"], dp_ratio)
        self.reg_layers = make_fc_layers(pre_channel, self.box_coder.code_size * self.num_class,
                                         model_cfg["REG_FC"], dp_ratio)
        self.init_weights()

    def init_weights(self):
        """Xavier-normal convs with zero bias; the last regression conv N(0, 0.001)."""
        for m in self.modules():
            if isinstance(m, (nn.Conv1d, nn.Conv2d)):
                nn.init.xavier_normal_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        nn.init.normal_(self.reg_layers[-1].weight, mean=0.0, std=0.001)

    def roi_grid_pool(self, batch_dict: dict) -> torch.Tensor:
        """Pooled keypoint features ``(B * num_rois, G^3, C)``."""
        batch_size = int(batch_dict["batch_size"])
        rois = batch_dict["rois"]
        point_coords = batch_dict["point_coords"]
        point_features = batch_dict["point_features"] * batch_dict["point_cls_scores"].view(-1, 1)

        grid = VoxelRCNNHead.grid_points_of_rois(rois, self.grid_size)  # (B*R, G^3, 3)
        new_xyz = grid.reshape(-1, 3).contiguous()
        per_sample = grid.shape[0] // batch_size * grid.shape[1]
        new_xyz_batch_cnt = torch.full((batch_size,), per_sample, dtype=torch.int32, device=new_xyz.device)
        _, pooled = self.roi_grid_pool_layer(
            xyz=point_coords[:, 1:4].contiguous(),
            xyz_batch_cnt=batch_counts(point_coords[:, 0], batch_size),
            new_xyz=new_xyz,
            new_xyz_batch_cnt=new_xyz_batch_cnt,
            features=point_features.contiguous(),
        )
        return pooled.view(-1, self.grid_size ** 3, pooled.shape[-1])

    def forward(self, batch_dict: dict) -> dict:
        nms_config = self.model_cfg["NMS_CONFIG"]["TRAIN" if self.training else "TEST"]
        self.proposal_layer(batch_dict, nms_config=nms_config)
        if self.training:
            targets_dict = self.assign_targets(batch_dict)
            batch_dict["rois"] = targets_dict["rois"]
            batch_dict["roi_labels"] = targets_dict["roi_labels"]

        pooled = self.roi_grid_pool(batch_dict)  # (B*R, G^3, C)
        n_rois = pooled.shape[0]
        # channel-major flattening: (B*R, C * G^3, 1)
        shared = self.shared_fc_layer(pooled.permute(0, 2, 1).reshape(n_rois, -1, 1))
        rcnn_cls = self.cls_layers(shared).transpose(1, 2).reshape(n_rois, -1)
        rcnn_reg = self.reg_layers(shared).transpose(1, 2).reshape(n_rois, -1)

        if not self.training:
            cls_preds, box_preds = self.generate_predicted_boxes(
                batch_size=int(batch_dict["batch_size"]), rois=batch_dict["rois"], cls_preds=rcnn_cls, box_preds=rcnn_reg
            )
            batch_dict["batch_cls_preds"] = cls_preds
            batch_dict["batch_box_preds"] = box_preds
            batch_dict["cls_preds_normalized"] = False
        else:
            targets_dict["rcnn_cls"] = rcnn_cls
            targets_dict["rcnn_reg"] = rcnn_reg
            self.forward_ret_dict = targets_dict
        return batch_dict
