"""AnchorHeadSingle (OpenPCDet dense_heads): 1x1 conv class / box / direction
predictions per anchor, targets from AxisAlignedTargetAssigner, OpenPCDet's losses."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from omnilidar.downstream.det.models import losses
from omnilidar.downstream.det.models.anchor_generator import generate_anchors
from omnilidar.downstream.det.models.box_coder import build_box_coder
from omnilidar.downstream.det.models.box_utils import limit_period
from omnilidar.downstream.det.models.target_assigner import AxisAlignedTargetAssigner


class AnchorHeadSingle(nn.Module):
    def __init__(self, model_cfg: dict, input_channels: int, num_class: int, class_names: list[str],
                 grid_size, point_cloud_range, predict_boxes_when_training: bool = True,
                 generator: torch.Generator | None = None, **_):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_class = 1 if model_cfg.get("CLASS_AGNOSTIC", False) else num_class
        self.class_names = list(class_names)
        self.predict_boxes_when_training = predict_boxes_when_training
        target_cfg = model_cfg["TARGET_ASSIGNER_CONFIG"]
        self.box_coder = build_box_coder(target_cfg.get("BOX_CODER", "ResidualCoder"),
                                         **target_cfg.get("BOX_CODER_CONFIG", {}))
        anchors, per_location = generate_anchors(point_cloud_range, model_cfg["ANCHOR_GENERATOR_CONFIG"], grid_size)
        self.anchors = anchors  # per class; moved to the predictions' device on use
        self.num_anchors_per_location = sum(per_location)
        if target_cfg.get("NAME", "AxisAlignedTargetAssigner") != "AxisAlignedTargetAssigner":
            raise ValueError(f"TARGET_ASSIGNER_CONFIG.NAME {target_cfg['NAME']!r} is not supported")
        self.target_assigner = AxisAlignedTargetAssigner(model_cfg, class_names, self.box_coder,
                                                         generator or torch.Generator().manual_seed(0))
        a = self.num_anchors_per_location
        self.conv_cls = nn.Conv2d(input_channels, a * self.num_class, kernel_size=1)
        self.conv_box = nn.Conv2d(input_channels, a * self.box_coder.code_size, kernel_size=1)
        self.use_dir = model_cfg.get("USE_DIRECTION_CLASSIFIER") is not None
        self.conv_dir_cls = nn.Conv2d(input_channels, a * int(model_cfg["NUM_DIR_BINS"]), kernel_size=1) \
            if self.use_dir else None
        self.forward_ret_dict: dict = {}
        pi = 0.01
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - pi) / pi))
        nn.init.normal_(self.conv_box.weight, mean=0, std=0.001)

    def _flat_anchors(self, device) -> torch.Tensor:
        self.anchors = [a.to(device) for a in self.anchors]
        return torch.cat(self.anchors, dim=-3).view(-1, 7)

    def forward(self, data_dict: dict) -> dict:
        x = data_dict["spatial_features_2d"]
        cls_preds = self.conv_cls(x).permute(0, 2, 3, 1).contiguous()
        box_preds = self.conv_box(x).permute(0, 2, 3, 1).contiguous()
        dir_preds = self.conv_dir_cls(x).permute(0, 2, 3, 1).contiguous() if self.conv_dir_cls is not None else None
        self.forward_ret_dict = {"cls_preds": cls_preds, "box_preds": box_preds, "dir_cls_preds": dir_preds}
        if self.training:
            self._flat_anchors(x.device)
            self.forward_ret_dict.update(self.target_assigner.assign_targets(self.anchors, data_dict["gt_boxes"]))
        if not self.training or self.predict_boxes_when_training:
            cls, boxes = self.generate_predicted_boxes(int(data_dict["batch_size"]), cls_preds, box_preds, dir_preds)
            data_dict["batch_cls_preds"] = cls
            data_dict["batch_box_preds"] = boxes
            data_dict["cls_preds_normalized"] = False
        return data_dict

    def generate_predicted_boxes(self, batch_size, cls_preds, box_preds, dir_cls_preds=None):
        """Decode every anchor: (B, N, num_class) logits and (B, N, 7) boxes."""
        anchors = self._flat_anchors(box_preds.device)
        n = anchors.shape[0]
        batch_anchors = anchors[None].expand(batch_size, n, 7)
        batch_cls = cls_preds.view(batch_size, n, -1).float()
        batch_box = self.box_coder.decode_torch(box_preds.view(batch_size, n, -1), batch_anchors)
        if dir_cls_preds is not None:
            offset = float(self.model_cfg["DIR_OFFSET"])
            limit_offset = float(self.model_cfg["DIR_LIMIT_OFFSET"])
            bins = int(self.model_cfg["NUM_DIR_BINS"])
            dir_labels = dir_cls_preds.view(batch_size, n, -1).argmax(dim=-1)
            period = 2 * math.pi / bins
            rot = limit_period(batch_box[..., 6] - offset, limit_offset, period)
            heading = rot + offset + period * dir_labels.to(batch_box.dtype)
            batch_box = torch.cat([batch_box[..., :6], heading[..., None], batch_box[..., 7:]], dim=-1)
        return batch_cls, batch_box

    def get_loss(self) -> tuple[torch.Tensor, dict]:
        cls_loss, tb = self._cls_loss()
        box_loss, tb_box = self._box_loss()
        tb.update(tb_box)
        rpn_loss = cls_loss + box_loss
        tb["rpn_loss"] = rpn_loss.item()
        return rpn_loss, tb

    def _cls_loss(self):
        ret = self.forward_ret_dict
        cls_preds, labels = ret["cls_preds"], ret["box_cls_labels"]
        batch_size = cls_preds.shape[0]
        cared, positives, negatives = labels >= 0, labels > 0, labels == 0
        cls_weights = (negatives.float() + positives.float())
        cls_weights = cls_weights / positives.sum(1, keepdim=True).float().clamp(min=1.0)
        if self.num_class == 1:
            labels = torch.where(positives, torch.ones_like(labels), labels)
        targets = (labels * cared.long()).long()
        one_hot = F.one_hot(targets, self.num_class + 1)[..., 1:].to(cls_preds.dtype)
        loss = losses.sigmoid_focal_loss(cls_preds.view(batch_size, -1, self.num_class), one_hot, cls_weights)
        weight = self.model_cfg["LOSS_CONFIG"]["LOSS_WEIGHTS"]["cls_weight"]
        loss = loss.sum() / batch_size * weight
        return loss, {"rpn_loss_cls": loss.item()}

    def _box_loss(self):
        ret = self.forward_ret_dict
        box_preds, labels, targets = ret["box_preds"], ret["box_cls_labels"], ret["box_reg_targets"]
        batch_size = box_preds.shape[0]
        positives = (labels > 0).float()
        reg_weights = positives / positives.sum(1, keepdim=True).clamp(min=1.0)
        anchors = self._flat_anchors(box_preds.device)[None].expand(batch_size, -1, 7)
        box_preds = box_preds.view(batch_size, -1, self.box_coder.code_size)
        pred_sin, target_sin = losses.add_sin_difference(box_preds, targets)
        weights_cfg = self.model_cfg["LOSS_CONFIG"]["LOSS_WEIGHTS"]
        loc = losses.weighted_smooth_l1(pred_sin, target_sin, reg_weights, weights_cfg["code_weights"])
        loc = loc.sum() / batch_size * weights_cfg["loc_weight"]
        total, tb = loc, {"rpn_loss_loc": loc.item()}
        if ret["dir_cls_preds"] is not None:
            bins = int(self.model_cfg["NUM_DIR_BINS"])
            dir_targets = losses.direction_targets(anchors, targets, float(self.model_cfg["DIR_OFFSET"]), bins)
            dir_logits = ret["dir_cls_preds"].view(batch_size, -1, bins)
            weights = positives / positives.sum(-1, keepdim=True).clamp(min=1.0)
            dir_loss = losses.weighted_cross_entropy(dir_logits, dir_targets, weights)
            dir_loss = dir_loss.sum() / batch_size * weights_cfg["dir_weight"]
            total = total + dir_loss
            tb["rpn_loss_dir"] = dir_loss.item()
        return total, tb
