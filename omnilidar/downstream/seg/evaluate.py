"""Inference and evaluation of a trained segmentor.

Predictions are made per voxel (no cap, no augmentation) and mapped back to
every point of the scan, then counted in one confusion matrix over all scans
of an evaluation set (:mod:`omnilidar.metrics.segmentation`): per-class IoU,
mIoU with the semantic-kitti-api convention (absent classes count as 0), the
nanmean variant beside it, and accuracy.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.downstream.seg.checkpoints import load_payload
from omnilidar.downstream.seg.dataset import SegCollate, SegScanDataset
from omnilidar.downstream.seg.label_spaces import LabelSpace, get_label_space
from omnilidar.downstream.seg.models import restore
from omnilidar.devices import resolve_device
from omnilidar.errors import InputError
from omnilidar.progress import ProgressLog
from omnilidar.io import semantickitti
from omnilidar.metrics.segmentation import ConfusionMatrix


def load_segmentor(path: str | Path, backend: str = "auto", device: str = "auto"):
    """(model in eval mode, payload) of a checkpoint written by the training stage."""
    payload = load_payload(path)
    dev = resolve_device(device)
    model = restore(payload["model"], payload["state_dict"], backend, dev, path)
    return model, payload


@torch.no_grad()
def predict_points(model: torch.nn.Module, scans: list[np.ndarray], voxel_size: float,
                   num_ids: int, paths: list | None = None, confidence: bool = False):
    """Train-id predictions (1..K, uint8) for every point of each scan; with ``confidence``,
    (predictions, softmax probability of the predicted class as float32) pairs."""
    coll = SegCollate(num_ids, voxel_size)
    items = [{"points": p, "labels": np.zeros(len(p), np.uint8), "path": (paths or [None] * len(scans))[i],
              "draw": None} for i, p in enumerate(scans)]
    batch = coll(items)["batch"]
    device = next(model.parameters()).device
    logits = model(batch.to(device))
    if confidence:  # softmax only where asked: plain predictions are the argmax of the logits
        prob, top = torch.softmax(logits.float(), dim=1).max(dim=1)
        prob = prob.cpu()
    else:
        top, prob = logits.argmax(1), torch.zeros(0)
    pred = (top + 1).to(torch.uint8).cpu()
    parts = batch.split_points(prob) if confidence else [None] * len(scans)
    out = []
    for scan, part, p_part, idx in zip(scans, batch.split_points(pred), parts,
                                       batch.split_points(batch.point_index)):
        full = np.zeros(len(scan), np.uint8)
        full[idx.numpy()] = part.numpy()
        if (full == 0).any():  # cannot happen without a voxel cap; never hand back ignore
            raise RuntimeError("some points received no prediction")
        if confidence:
            conf = np.zeros(len(scan), np.float32)
            conf[idx.numpy()] = p_part.numpy()
            out.append((full, conf))
        else:
            out.append(full)
    return out


def evaluate_records(model: torch.nn.Module, records: list[dict], space: LabelSpace, voxel_size: float,
                     batch_size: int = 1) -> dict:
    """Scores of ``model`` on labelled scan records (one confusion over all scans)."""
    if not records:
        raise InputError(None, "evaluation set holds no scans")
    data = SegScanDataset(records, space)
    conf = ConfusionMatrix(space.num_ids)
    started = time.time()
    points_total = 0
    progress = ProgressLog(len(data), "evaluated scans")
    for start in range(0, len(data), batch_size):
        items = [data[i] for i in range(start, min(start + batch_size, len(data)))]
        preds = predict_points(model, [it["points"] for it in items], voxel_size, space.num_ids,
                               [it["path"] for it in items])
        for it, pred in zip(items, preds):
            conf.update(it["labels"], pred, it["path"])
            points_total += len(pred)
        progress.step(len(items))
    scores = conf.result()
    return {
        **scores.as_dict(list(space.class_names)),
        "num_scans": len(records),
        "num_points": int(points_total),
        "confusion": conf.matrix.tolist(),
        "seconds": round(time.time() - started, 2),
    }


def semantickitti_dir_records(root: str | Path) -> list[dict]:
    """Labelled records of a SemanticKITTI-layout folder: ``sequences/*/`` or ``velodyne/`` + ``labels/``."""
    root = Path(root)
    seqs = sorted(p for p in (root / "sequences").glob("*") if p.is_dir()) if (root / "sequences").is_dir() else []
    records = []
    if seqs:
        for seq in seqs:
            for bin_path, label_path in semantickitti.sequence_paths(root, seq.name):
                if label_path is None:
                    raise InputError(bin_path.parent.parent, "sequence has no labels/ folder")
                records.append({"points": str(bin_path), "labels": str(label_path), "format": "semantickitti"})
    else:
        velo = root / "velodyne"
        if not velo.is_dir():
            raise InputError(root, "holds neither sequences/ nor velodyne/")
        for bin_path in sorted(velo.glob("*.bin")):
            records.append({"points": str(bin_path), "labels": str(root / "labels" / f"{bin_path.stem}.label"),
                            "format": "semantickitti"})
    if not records:
        raise InputError(root, "holds no scans")
    return records


def label_space_of(payload: dict) -> LabelSpace:
    return get_label_space(payload["label_space"])

