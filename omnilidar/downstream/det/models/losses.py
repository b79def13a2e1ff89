"""OpenPCDet's detection losses (pcdet.utils.loss_utils), element-wise, unreduced."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from omnilidar.downstream.det.models.box_utils import boxes_to_corners_3d, limit_period


def sigmoid_focal_loss(logits, targets, weights, alpha: float = 0.25, gamma: float = 2.0):
    """(B, N, C) focal loss of one-hot ``targets``, times anchor ``weights`` (B, N)."""
    p = torch.sigmoid(logits)
    alpha_weight = targets * alpha + (1 - targets) * (1 - alpha)
    pt = targets * (1.0 - p) + (1.0 - targets) * p
    bce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    return alpha_weight * pt.pow(gamma) * bce * weights.unsqueeze(-1)


def smooth_l1(diff: torch.Tensor, beta: float) -> torch.Tensor:
    n = diff.abs()
    if beta < 1e-5:
        return n
    return torch.where(n < beta, 0.5 * n ** 2 / beta, n - 0.5 * beta)


def weighted_smooth_l1(pred, target, weights=None, code_weights=None, beta: float = 1.0 / 9.0):
    """(B, N, C) smooth-L1 of ``pred - target`` (NaN targets count as exact),
    scaled per code by ``code_weights`` and per row by ``weights`` (B, N)."""
    target = torch.where(torch.isnan(target), pred, target)
    diff = pred - target
    if code_weights is not None:
        diff = diff * diff.new_tensor(code_weights)
    loss = smooth_l1(diff, beta)
    return loss if weights is None else loss * weights.unsqueeze(-1)


def weighted_cross_entropy(logits, one_hot_targets, weights):
    """(B, N, K) logits, one-hot targets -> (B, N) cross-entropy times ``weights``."""
    return F.cross_entropy(logits.permute(0, 2, 1), one_hot_targets.argmax(dim=-1), reduction="none") * weights


def add_sin_difference(boxes1, boxes2, dim: int = 6):
    """Replace headings a, b by sin(a)cos(b), cos(a)sin(b): their difference is sin(a - b)."""
    a, b = boxes1[..., dim:dim + 1], boxes2[..., dim:dim + 1]
    boxes1 = torch.cat([boxes1[..., :dim], torch.sin(a) * torch.cos(b), boxes1[..., dim + 1:]], dim=-1)
    boxes2 = torch.cat([boxes2[..., :dim], torch.cos(a) * torch.sin(b), boxes2[..., dim + 1:]], dim=-1)
    return boxes1, boxes2


def direction_targets(anchors, reg_targets, dir_offset: float, num_bins: int):
    """One-hot heading bin of the target box (anchor heading + residual)."""
    rot = reg_targets[..., 6] + anchors[..., 6]
    offset_rot = limit_period(rot - dir_offset, 0, 2 * math.pi)
    bins = torch.floor(offset_rot / (2 * math.pi / num_bins)).long().clamp(0, num_bins - 1)
    return F.one_hot(bins, num_bins).to(anchors.dtype)


def corner_loss(pred_boxes, gt_boxes):
    """(N,) mean over corners of Huber(1.0) corner distance, the nearer of gt and gt flipped by pi."""
    pred = boxes_to_corners_3d(pred_boxes)
    gt = boxes_to_corners_3d(gt_boxes)
    flipped = gt_boxes.clone()
    flipped[:, 6] += math.pi
    gt_flip = boxes_to_corners_3d(flipped)
    dist = torch.minimum((pred - gt).norm(dim=2), (pred - gt_flip).norm(dim=2))
    return smooth_l1(dist, 1.0).mean(dim=1)
