"""RoIHeadTemplate (OpenPCDet roi_heads): proposals by NMS on the dense head's
boxes, RoI targets in the RoI's canonical frame, the refinement losses, and
decoding refined boxes."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from omnilidar.downstream.det.models import losses
from omnilidar.downstream.det.models.box_coder import build_box_coder
from omnilidar.downstream.det.models.box_utils import rotate_points_along_z
from omnilidar.downstream.det.models.proposal_target_layer import ProposalTargetLayer
from omnilidar.downstream.det.ops.nms import class_agnostic_nms


class RoIHeadTemplate(nn.Module):
    def __init__(self, num_class: int, model_cfg: dict, generator: torch.Generator | None = None):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_class = num_class
        target_cfg = model_cfg["TARGET_CONFIG"]
        self.box_coder = build_box_coder(target_cfg.get("BOX_CODER", "ResidualCoder"),
                                         **target_cfg.get("BOX_CODER_CONFIG", {}))
        self.proposal_target_layer = ProposalTargetLayer(target_cfg, generator or torch.Generator().manual_seed(0))
        self.forward_ret_dict: dict = {}

    @torch.no_grad()
    def proposal_layer(self, batch_dict: dict, nms_config: dict) -> dict:
        """Top NMS_POST_MAXSIZE boxes per sample after class-agnostic NMS (zero-padded)."""
        if batch_dict.get("rois") is not None:
            return batch_dict
        if nms_config.get("MULTI_CLASSES_NMS", False):
            raise ValueError("ROI_HEAD.NMS_CONFIG.MULTI_CLASSES_NMS is not supported (as in OpenPCDet)")
        batch_size = int(batch_dict["batch_size"])
        box_preds_all, cls_preds_all = batch_dict["batch_box_preds"], batch_dict["batch_cls_preds"]
        post = int(nms_config["NMS_POST_MAXSIZE"])
        rois = box_preds_all.new_zeros((batch_size, post, box_preds_all.shape[-1]))
        roi_scores = box_preds_all.new_zeros((batch_size, post))
        roi_labels = torch.zeros((batch_size, post), dtype=torch.long, device=box_preds_all.device)
        for b in range(batch_size):
            if batch_dict.get("batch_index") is not None:
                mask = batch_dict["batch_index"] == b
            else:
                mask = b
            box_preds, cls_preds = box_preds_all[mask], cls_preds_all[mask]
            scores, labels = cls_preds.max(dim=1)
            selected, _ = class_agnostic_nms(scores, box_preds, nms_config)
            rois[b, :len(selected)] = box_preds[selected]
            roi_scores[b, :len(selected)] = scores[selected]
            roi_labels[b, :len(selected)] = labels[selected]
        batch_dict["rois"] = rois
        batch_dict["roi_scores"] = roi_scores
        batch_dict["roi_labels"] = roi_labels + 1
        batch_dict["has_class_labels"] = cls_preds_all.shape[-1] > 1
        batch_dict.pop("batch_index", None)
        return batch_dict

    def assign_targets(self, batch_dict: dict) -> dict:
        """Sampled RoIs and their gt boxes expressed in each RoI's frame, heading in (-pi/2, pi/2]."""
        batch_size = int(batch_dict["batch_size"])
        with torch.no_grad():
            targets = self.proposal_target_layer.forward(batch_dict)
        rois, gt = targets["rois"], targets["gt_of_rois"]
        targets["gt_of_rois_src"] = gt.clone().detach()
        roi_ry = rois[:, :, 6] % (2 * math.pi)
        gt = gt.clone()
        gt[:, :, 0:3] = gt[:, :, 0:3] - rois[:, :, 0:3]
        gt[:, :, 6] = gt[:, :, 6] - roi_ry
        gt = rotate_points_along_z(gt.view(-1, 1, gt.shape[-1]), -roi_ry.view(-1)).view(batch_size, -1, gt.shape[-1])
        heading = gt[:, :, 6] % (2 * math.pi)
        opposite = (heading > math.pi * 0.5) & (heading < math.pi * 1.5)
        heading = torch.where(opposite, (heading + math.pi) % (2 * math.pi), heading)
        heading = torch.where(heading > math.pi, heading - 2 * math.pi, heading)
        gt[:, :, 6] = heading.clamp(min=-math.pi / 2, max=math.pi / 2)
        targets["gt_of_rois"] = gt
        return targets

    def get_box_reg_layer_loss(self, ret: dict):
        cfg = self.model_cfg["LOSS_CONFIG"]
        weights = cfg["LOSS_WEIGHTS"]
        code_size = self.box_coder.code_size
        fg_mask = ret["reg_valid_mask"].view(-1) > 0
        fg_sum = int(fg_mask.sum())
        gt_ct = ret["gt_of_rois"][..., :code_size]
        gt_src = ret["gt_of_rois_src"][..., :code_size].view(-1, code_size)
        rcnn_reg = ret["rcnn_reg"]
        rois = ret["rois"]
        n = gt_ct.view(-1, code_size).shape[0]
        if cfg.get("REG_LOSS", "smooth-l1") != "smooth-l1":
            raise ValueError(f"ROI_HEAD.LOSS_CONFIG.REG_LOSS {cfg['REG_LOSS']!r} is not supported")
        anchors = rois.clone().detach().view(-1, code_size)
        anchors[:, 0:3] = 0
        anchors[:, 6] = 0
        reg_targets = self.box_coder.encode_torch(gt_ct.view(n, code_size), anchors)
        loss = losses.weighted_smooth_l1(rcnn_reg.view(n, -1)[None], reg_targets[None],
                                         code_weights=weights["code_weights"])
        loss = (loss.view(n, -1) * fg_mask[:, None].float()).sum() / max(fg_sum, 1)
        loss = loss * weights["rcnn_reg_weight"]
        tb = {"rcnn_loss_reg": loss.item()}
        if cfg.get("CORNER_LOSS_REGULARIZATION", False) and fg_sum > 0:
            fg_reg = rcnn_reg.view(n, -1)[fg_mask]
            fg_rois = rois.view(-1, code_size)[fg_mask]
            local = fg_rois.clone().detach()
            local[:, 0:3] = 0
            boxes = self.box_coder.decode_torch(fg_reg, local)
            boxes = rotate_points_along_z(boxes[:, None], fg_rois[:, 6])[:, 0]
            boxes = torch.cat([boxes[:, 0:3] + fg_rois[:, 0:3], boxes[:, 3:]], dim=1)
            corner = losses.corner_loss(boxes[:, :7], gt_src[fg_mask][:, :7]).mean()
            corner = corner * weights["rcnn_corner_weight"]
            loss = loss + corner
            tb["rcnn_loss_corner"] = corner.item()
        return loss, tb

    def get_box_cls_layer_loss(self, ret: dict):
        cfg = self.model_cfg["LOSS_CONFIG"]
        rcnn_cls, labels = ret["rcnn_cls"], ret["rcnn_cls_labels"].view(-1)
        valid = (labels >= 0).float()
        if cfg["CLS_LOSS"] == "BinaryCrossEntropy":
            per_roi = F.binary_cross_entropy(torch.sigmoid(rcnn_cls.view(-1)), labels.float(), reduction="none")
        elif cfg["CLS_LOSS"] == "CrossEntropy":
            per_roi = F.cross_entropy(rcnn_cls, labels.long(), reduction="none", ignore_index=-1)
        else:
            raise ValueError(f"ROI_HEAD.LOSS_CONFIG.CLS_LOSS {cfg['CLS_LOSS']!r} is not supported")
        loss = (per_roi * valid).sum() / valid.sum().clamp(min=1.0)
        loss = loss * cfg["LOSS_WEIGHTS"]["rcnn_cls_weight"]
        return loss, {"rcnn_loss_cls": loss.item()}

    def get_loss(self, tb_dict: dict | None = None):
        tb = {} if tb_dict is None else tb_dict
        cls_loss, cls_tb = self.get_box_cls_layer_loss(self.forward_ret_dict)
        reg_loss, reg_tb = self.get_box_reg_layer_loss(self.forward_ret_dict)
        tb.update(cls_tb)
        tb.update(reg_tb)
        loss = cls_loss + reg_loss
        tb["rcnn_loss"] = loss.item()
        return loss, tb

    def generate_predicted_boxes(self, batch_size: int, rois, cls_preds, box_preds):
        """Refined boxes: residuals decoded in each RoI's frame, rotated and moved back."""
        code_size = self.box_coder.code_size
        batch_cls = cls_preds.view(batch_size, -1, cls_preds.shape[-1])
        local = rois.clone().detach()
        local[:, :, 0:3] = 0
        boxes = self.box_coder.decode_torch(box_preds.view(batch_size, -1, code_size), local).view(-1, code_size)
        boxes = rotate_points_along_z(boxes[:, None], rois[:, :, 6].reshape(-1))[:, 0]
        boxes = torch.cat([boxes[:, 0:3] + rois[:, :, 0:3].reshape(-1, 3), boxes[:, 3:]], dim=1)
        return batch_cls, boxes.view(batch_size, -1, code_size)
