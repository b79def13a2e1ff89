"""PV-RCNN's keypoint segmentation head (OpenPCDet's PointHeadSimple).

An MLP (``cls_layers``: Linear-BN-ReLU per ``CLS_FC`` entry, then a Linear to the
classes) scores every keypoint as foreground. The scores
(``point_cls_scores``, sigmoid, max over classes) weight the keypoint features in
the RoI head. Training targets: a keypoint inside a ground-truth box is
foreground (class 1 when class-agnostic, else the box's class); a keypoint inside
the box enlarged by ``GT_EXTRA_WIDTH`` but not the box itself is ignored; all
others are background. Loss: sigmoid focal loss (alpha 0.25, gamma 2) summed and
normalised by the number of foreground keypoints.

Zero-padded gt rows (class 0) are skipped. OpenPCDet enlarges them too, into
GT_EXTRA_WIDTH-sized boxes at the origin whose keypoints it then ignores.
"""

from __future__ import annotations

import torch
from torch import nn

from omnilidar.downstream.det.models.losses import sigmoid_focal_loss
from omnilidar.geometry.points_in_boxes import points_in_boxes


def enlarge_boxes(boxes: torch.Tensor, extra_width) -> torch.Tensor:
    """Boxes ``(N, 7+)`` with ``extra_width`` added to dx, dy, dz (OpenPCDet's enlarge_box3d)."""
    out = boxes.clone()
    out[:, 3:6] += boxes.new_tensor(extra_width)[None, :]
    return out


class PointHeadSimple(nn.Module):
    def __init__(self, num_class: int, input_channels: int, model_cfg: dict, **kwargs):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_class = int(num_class)
        self.extra_width = list(model_cfg.get("TARGET_CONFIG", {}).get("GT_EXTRA_WIDTH", [0.0, 0.0, 0.0]))
        self.cls_weight = float(model_cfg.get("LOSS_CONFIG", {}).get("LOSS_WEIGHTS", {}).get("point_cls_weight", 1.0))
        layers: list[nn.Module] = []
        c_in = int(input_channels)
        for c in model_cfg["CLS_FC"]:
            layers += [nn.Linear(c_in, c, bias=False), nn.BatchNorm1d(c), nn.ReLU()]
            c_in = c
        layers.append(nn.Linear(c_in, self.num_class, bias=True))
        self.cls_layers = nn.Sequential(*layers)
        self.forward_ret_dict: dict | None = None

    @torch.no_grad()
    def assign_targets(self, point_coords: torch.Tensor, gt_boxes: torch.Tensor) -> torch.Tensor:
        """Per keypoint: 0 background, -1 ignored, else the class (1 when class-agnostic).

        point_coords: ``(K, 4)`` [batch, x, y, z]; gt_boxes: ``(B, M, 8)`` with class
        ids from 1 and all-zero padding rows (class 0, skipped).
        """
        if gt_boxes.dim() != 3 or gt_boxes.shape[2] != 8:
            raise ValueError(f"gt_boxes must be (B, M, 8), got {tuple(gt_boxes.shape)}")
        labels = point_coords.new_zeros(point_coords.shape[0], dtype=torch.long)
        for b in range(gt_boxes.shape[0]):
            in_sample = point_coords[:, 0] == b
            boxes = gt_boxes[b][gt_boxes[b, :, 7] > 0]
            if boxes.shape[0] == 0 or not bool(in_sample.any()):
                continue
            xyz = point_coords[in_sample, 1:4].contiguous()
            box_of_point = points_in_boxes(xyz, boxes[:, :7].contiguous())
            in_extended = points_in_boxes(xyz, enlarge_boxes(boxes[:, :7], self.extra_width)) >= 0
            fg = box_of_point >= 0
            single = torch.zeros_like(box_of_point)
            single[fg ^ in_extended] = -1
            if self.num_class == 1:
                single[fg] = 1
            else:
                single[fg] = boxes[box_of_point[fg], 7].long()
            labels[in_sample] = single
        return labels

    def forward(self, batch_dict: dict) -> dict:
        """Adds ``point_cls_scores`` (K,) to ``batch_dict``; keeps what the loss needs."""
        if self.model_cfg.get("USE_POINT_FEATURES_BEFORE_FUSION", False):
            features = batch_dict["point_features_before_fusion"]
        else:
            features = batch_dict["point_features"]
        preds = self.cls_layers(features)
        batch_dict["point_cls_scores"] = torch.sigmoid(preds).amax(dim=-1)
        ret = {"point_cls_preds": preds}
        if self.training:
            ret["point_cls_labels"] = self.assign_targets(batch_dict["point_coords"], batch_dict["gt_boxes"])
        self.forward_ret_dict = ret
        return batch_dict

    def get_loss(self, tb_dict: dict | None = None):
        tb_dict = {} if tb_dict is None else tb_dict
        labels = self.forward_ret_dict["point_cls_labels"].view(-1)
        preds = self.forward_ret_dict["point_cls_preds"].view(-1, self.num_class)
        positives = labels > 0
        weights = ((labels == 0) | positives).float()
        num_pos = positives.sum().float()
        weights = weights / num_pos.clamp(min=1.0)
        one_hot = preds.new_zeros(labels.shape[0], self.num_class + 1)
        one_hot.scatter_(1, labels.clamp(min=0).unsqueeze(1), 1.0)
        loss = sigmoid_focal_loss(preds, one_hot[:, 1:], weights).sum() * self.cls_weight
        tb_dict.update({"point_loss_cls": float(loss.detach()), "point_pos_num": float(num_pos)})
        return loss, tb_dict
