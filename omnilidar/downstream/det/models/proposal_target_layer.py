"""OpenPCDet's ProposalTargetLayer: sample ROI_PER_IMAGE RoIs per sample by 3D
IoU with the ground truth (foreground share FG_RATIO, hard/easy background split
HARD_BG_RATIO) and give each its regression and classification targets."""

from __future__ import annotations

import torch

from omnilidar.downstream.det.models.box_utils import strip_padding
from omnilidar.geometry.rotated_iou import boxes_iou3d


class ProposalTargetLayer:
    def __init__(self, cfg: dict, generator: torch.Generator):
        self.cfg = cfg
        self.generator = generator  # CPU generator for every sampling draw

    def forward(self, batch_dict: dict) -> dict:
        rois, gt_of_rois, ious, scores, labels = self.sample_rois_for_rcnn(batch_dict)
        cfg = self.cfg
        reg_valid_mask = (ious > cfg["REG_FG_THRESH"]).long()
        fg_thresh, bg_thresh = cfg["CLS_FG_THRESH"], cfg["CLS_BG_THRESH"]
        if cfg["CLS_SCORE_TYPE"] == "cls":
            cls_labels = (ious > fg_thresh).long()
            cls_labels[(ious > bg_thresh) & (ious < fg_thresh)] = -1
        elif cfg["CLS_SCORE_TYPE"] == "roi_iou":
            fg, bg = ious > fg_thresh, ious < bg_thresh
            between = ~fg & ~bg
            cls_labels = fg.float()
            cls_labels[between] = (ious[between] - bg_thresh) / (fg_thresh - bg_thresh)
        else:
            raise ValueError(f"CLS_SCORE_TYPE {cfg['CLS_SCORE_TYPE']!r} is not 'cls' or 'roi_iou'")
        return {"rois": rois, "gt_of_rois": gt_of_rois, "gt_iou_of_rois": ious, "roi_scores": scores,
                "roi_labels": labels, "reg_valid_mask": reg_valid_mask, "rcnn_cls_labels": cls_labels}

    def sample_rois_for_rcnn(self, batch_dict: dict):
        n = int(self.cfg["ROI_PER_IMAGE"])
        rois, roi_scores, roi_labels = batch_dict["rois"], batch_dict["roi_scores"], batch_dict["roi_labels"]
        out_rois, out_gt, out_ious, out_scores, out_labels = [], [], [], [], []
        for b in range(int(batch_dict["batch_size"])):
            cur_roi, cur_labels = rois[b], roi_labels[b]
            gt = strip_padding(batch_dict["gt_boxes"][b])
            if len(gt) == 0:
                gt = gt.new_zeros((1, gt.shape[1]))
            if self.cfg.get("SAMPLE_ROI_BY_EACH_CLASS", False):
                max_iou, assignment = self._max_iou_same_class(cur_roi, cur_labels, gt[:, :7], gt[:, -1].long())
            else:
                max_iou, assignment = boxes_iou3d(cur_roi[:, :7], gt[:, :7]).max(dim=1)
            picked = self.subsample_rois(max_iou)
            out_rois.append(cur_roi[picked])
            out_labels.append(cur_labels[picked])
            out_ious.append(max_iou[picked])
            out_scores.append(roi_scores[b][picked])
            out_gt.append(gt[assignment[picked]])
        return (torch.stack(out_rois), torch.stack(out_gt), torch.stack(out_ious),
                torch.stack(out_scores), torch.stack(out_labels))

    def _randint(self, high: int, size: int, device) -> torch.Tensor:
        return torch.randint(0, high, (size,), generator=self.generator).to(device)

    def subsample_rois(self, max_iou: torch.Tensor) -> torch.Tensor:
        cfg, dev = self.cfg, max_iou.device
        n = int(cfg["ROI_PER_IMAGE"])
        fg_per_image = int(round(cfg["FG_RATIO"] * n))
        fg_thresh = min(cfg["REG_FG_THRESH"], cfg["CLS_FG_THRESH"])
        fg = (max_iou >= fg_thresh).nonzero().view(-1)
        easy_bg = (max_iou < cfg["CLS_BG_THRESH_LO"]).nonzero().view(-1)
        hard_bg = ((max_iou < cfg["REG_FG_THRESH"]) & (max_iou >= cfg["CLS_BG_THRESH_LO"])).nonzero().view(-1)
        num_bg = len(hard_bg) + len(easy_bg)
        if len(fg) > 0 and num_bg > 0:
            n_fg = min(fg_per_image, len(fg))
            fg = fg[torch.randperm(len(fg), generator=self.generator)[:n_fg].to(dev)]
            bg = self._sample_bg(hard_bg, easy_bg, n - n_fg)
        elif len(fg) > 0:
            fg = fg[self._randint(len(fg), n, dev)]
            bg = fg[:0]
        elif num_bg > 0:
            bg = self._sample_bg(hard_bg, easy_bg, n)
        else:
            raise ValueError(f"no RoI to sample: max IoU in [{float(max_iou.min())}, {float(max_iou.max())}]")
        return torch.cat([fg, bg])

    def _sample_bg(self, hard: torch.Tensor, easy: torch.Tensor, count: int) -> torch.Tensor:
        dev = hard.device
        if len(hard) > 0 and len(easy) > 0:
            n_hard = min(int(count * self.cfg["HARD_BG_RATIO"]), len(hard))
            return torch.cat([hard[self._randint(len(hard), n_hard, dev)],
                              easy[self._randint(len(easy), count - n_hard, dev)]])
        pool = hard if len(hard) > 0 else easy
        return pool[self._randint(len(pool), count, dev)]

    @staticmethod
    def _max_iou_same_class(rois, roi_labels, gt_boxes, gt_labels):
        max_iou = rois.new_zeros(rois.shape[0])
        assignment = roi_labels.new_zeros(roi_labels.shape[0])
        for k in range(int(gt_labels.min()), int(gt_labels.max()) + 1):
            roi_mask, gt_mask = roi_labels == k, gt_labels == k
            if roi_mask.any() and gt_mask.any():
                iou = boxes_iou3d(rois[roi_mask][:, :7], gt_boxes[gt_mask])
                best, which = iou.max(dim=1)
                max_iou[roi_mask] = best
                assignment[roi_mask] = gt_mask.nonzero().view(-1)[which]
        return max_iou, assignment
