"""OpenPCDet's AxisAlignedTargetAssigner: anchors -> class labels, box residuals,
regression weights, matching by (rounded-heading) BEV IoU per class."""

from __future__ import annotations

import torch

from omnilidar.downstream.det.models.box_utils import strip_padding
from omnilidar.geometry.rotated_iou import boxes_iou3d, boxes_iou_bev_nearest


class AxisAlignedTargetAssigner:
    def __init__(self, model_cfg: dict, class_names: list[str], box_coder, generator: torch.Generator):
        anchor_cfgs = model_cfg["ANCHOR_GENERATOR_CONFIG"]
        target_cfg = model_cfg["TARGET_ASSIGNER_CONFIG"]
        self.box_coder = box_coder
        self.match_height = bool(target_cfg.get("MATCH_HEIGHT", False))
        self.class_names = list(class_names)
        self.anchor_class_names = [c["class_name"] for c in anchor_cfgs]
        pos_fraction = float(target_cfg.get("POS_FRACTION", -1.0))
        self.pos_fraction = pos_fraction if pos_fraction >= 0 else None
        self.sample_size = int(target_cfg.get("SAMPLE_SIZE", 512))
        self.norm_by_num_examples = bool(target_cfg.get("NORM_BY_NUM_EXAMPLES", False))
        self.matched = {c["class_name"]: float(c["matched_threshold"]) for c in anchor_cfgs}
        self.unmatched = {c["class_name"]: float(c["unmatched_threshold"]) for c in anchor_cfgs}
        self.generator = generator

    def assign_targets(self, all_anchors: list[torch.Tensor], gt_boxes_with_classes: torch.Tensor) -> dict:
        """``all_anchors`` per class (Z, Y, X, sizes, rotations, 7); ``gt_boxes`` (B, M, 8).
        Returns box_cls_labels (B, N), box_reg_targets (B, N, code), reg_weights (B, N)."""
        labels_b, targets_b, weights_b = [], [], []
        for sample in gt_boxes_with_classes:
            gt = strip_padding(sample)
            gt_classes = gt[:, -1].long()
            per_class = []
            for name, anchors in zip(self.anchor_class_names, all_anchors):
                mask = torch.tensor([self.class_names[c - 1] == name for c in gt_classes.tolist()],
                                    dtype=torch.bool, device=gt.device)
                fmap = anchors.shape[:3]
                result = self.assign_single(anchors.view(-1, anchors.shape[-1]), gt[mask][:, :-1],
                                            gt_classes[mask], self.matched[name], self.unmatched[name])
                per_class.append([result[0].view(*fmap, -1), result[1].view(*fmap, -1, self.box_coder.code_size),
                                  result[2].view(*fmap, -1)])
            labels_b.append(torch.cat([p[0] for p in per_class], dim=-1).view(-1))
            targets_b.append(torch.cat([p[1] for p in per_class], dim=-2).view(-1, self.box_coder.code_size))
            weights_b.append(torch.cat([p[2] for p in per_class], dim=-1).view(-1))
        return {"box_cls_labels": torch.stack(labels_b), "box_reg_targets": torch.stack(targets_b),
                "reg_weights": torch.stack(weights_b)}

    def assign_single(self, anchors, gt_boxes, gt_classes, matched_threshold, unmatched_threshold):
        n = anchors.shape[0]
        dev = anchors.device
        labels = torch.full((n,), -1, dtype=torch.long, device=dev)
        has_gt = len(gt_boxes) > 0 and n > 0
        if has_gt:
            overlap = boxes_iou3d(anchors[:, :7], gt_boxes[:, :7]) if self.match_height \
                else boxes_iou_bev_nearest(anchors[:, :7], gt_boxes[:, :7])
            anchor_max, anchor_argmax = overlap.max(dim=1)
            gt_max = overlap.max(dim=0).values
            gt_max = torch.where(gt_max == 0, torch.full_like(gt_max, -1), gt_max)
            # Every gt's best anchors (ties included) are positive whatever their IoU.
            forced = (overlap == gt_max[None]).nonzero()[:, 0]
            gt_forced = anchor_argmax[forced]
            labels[forced] = gt_classes[gt_forced]
            pos = anchor_max >= matched_threshold
            labels[pos] = gt_classes[anchor_argmax[pos]]
            bg = (anchor_max < unmatched_threshold).nonzero()[:, 0]
        else:
            bg = torch.arange(n, device=dev)
        fg = (labels > 0).nonzero()[:, 0]
        if self.pos_fraction is not None:
            num_fg = int(self.pos_fraction * self.sample_size)
            if len(fg) > num_fg:
                disable = torch.randperm(len(fg), generator=self.generator)[: len(fg) - num_fg].to(dev)
                labels[fg[disable]] = -1
                fg = (labels > 0).nonzero()[:, 0]
            num_bg = self.sample_size - int((labels > 0).sum())
            if len(bg) > num_bg:
                pick = torch.randint(0, len(bg), (num_bg,), generator=self.generator).to(dev)
                labels[bg[pick]] = 0
        elif has_gt:
            labels[bg] = 0
            labels[forced] = gt_classes[gt_forced]
        else:
            labels[:] = 0
        targets = anchors.new_zeros((n, self.box_coder.code_size))
        if has_gt:
            targets[fg] = self.box_coder.encode_torch(gt_boxes[anchor_argmax[fg]], anchors[fg])
        weights = anchors.new_zeros((n,))
        if self.norm_by_num_examples:
            weights[labels > 0] = 1.0 / max(float((labels >= 0).sum()), 1.0)
        else:
            weights[labels > 0] = 1.0
        return labels, targets, weights
