"""Running a trained detector over frames: boxes back in each frame's own LiDAR frame.

Frames go through the evaluation path of :class:`~.dataset.DetScanDataset`
(no augmentation, no shuffle, test voxel cap) in batches; the detector's
``pred_dicts`` are moved back by minus SHIFT_COOR and named by class. The
recall counters of OpenPCDet (``gt``, ``roi_0.3``, ``rcnn_0.3``, ...) are
summed over frames as its ``eval_one_epoch`` does.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from omnilidar.downstream.det.dataset import DetCollate, DetScanDataset, batch_to


@torch.no_grad()
def predict_frames(net: torch.nn.Module, dataset: DetScanDataset, batch_size: int, device,
                   log_every: int = 0) -> tuple[list[dict], dict, float]:
    """``(predictions, recall counts, seconds per frame)``; one prediction per frame:
    ``{"frame_id", "boxes" (K, 7) float32, "scores" (K,), "names" [K]}`` in the frame's own coordinates."""
    net.eval()
    collate = DetCollate()
    shift = np.asarray(dataset.cfg.shift, np.float32)
    names = np.array(dataset.cfg.class_names)
    out, recall = [], {}
    started = time.time()
    for start in range(0, len(dataset), batch_size):
        idx = list(range(start, min(start + batch_size, len(dataset))))
        batch = batch_to(collate([dataset[i] for i in idx]), device)
        pred_dicts, recall_dict = net(batch)
        for key, value in recall_dict.items():
            recall[key] = recall.get(key, 0) + float(value)
        for i, pred in zip(idx, pred_dicts):
            boxes = pred["pred_boxes"].detach().cpu().numpy().astype(np.float32).reshape(-1, 7)
            boxes[:, :3] -= shift
            labels = pred["pred_labels"].detach().cpu().numpy().astype(np.int64).reshape(-1)
            out.append({"frame_id": dataset.records[i]["frame_id"], "boxes": boxes,
                        "scores": pred["pred_scores"].detach().cpu().numpy().astype(np.float32).reshape(-1),
                        "names": names[labels - 1].tolist() if len(labels) else []})
        if log_every and (len(out) % log_every < batch_size or len(out) == len(dataset)):
            print(f"predicted {len(out)}/{len(dataset)} frames", flush=True)
    seconds = (time.time() - started) / max(len(dataset), 1)
    return out, recall, seconds


def recall_rates(recall: dict) -> dict:
    """OpenPCDet's recall numbers: each ``roi_*`` / ``rcnn_*`` count over ``gt``."""
    gt = max(float(recall.get("gt", 0)), 1.0)
    return {k: v / gt for k, v in sorted(recall.items()) if k != "gt"} | {"gt": int(recall.get("gt", 0))}
