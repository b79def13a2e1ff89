"""Pseudo-boxes for generated scans, written as Pi3DET infos, one shard per sample shard.

::

    OUT/infos.pkl      Pi3DET infos (frame_id = scan name, platform, point_clout_path
                       "velodyne/<name>.bin" relative to the sample shard, annos with the
                       labeler's boxes scoring >= the threshold, in the scan's own frame)
    OUT/sidecar.json   sample shard, threshold, boxes per class, labeler, seconds

Generated scans with no points get an info without boxes. A GDA run pairs each
pseudo-box shard with its sample shard (:func:`generated_records`) and fails
with one clear error when they do not match.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io import pi3det
from omnilidar.io.atomic import atomic_path
from omnilidar.lidar.scan import Boxes

INFOS = "infos.pkl"
SIDECAR = "sidecar.json"


def sample_scans(sample_dir: str | Path) -> list[Path]:
    """The ``velodyne/*.bin`` scans of a sample shard, sorted by name."""
    from omnilidar.downstream.seg.pseudo_label import sample_scans as scans

    return scans(sample_dir)


def threshold_boxes(pred: dict, min_score: float) -> tuple[np.ndarray, list[str]]:
    """Boxes (and names) scoring at least ``min_score`` with positive finite sizes."""
    boxes = np.asarray(pred["boxes"], np.float32).reshape(-1, 7)
    keep = (np.asarray(pred["scores"]) >= min_score) & np.isfinite(boxes).all(axis=1) & (boxes[:, 3:6] > 0).all(axis=1)
    return boxes[keep], [n for n, k in zip(pred["names"], keep) if k]


def write_shard(sample_dir: str | Path, platform_name: str, predictions: dict[str, dict], min_score: float,
                out: str | Path, labeler: dict, seconds: float) -> dict:
    """Write one pseudo-box shard atomically; ``predictions`` maps scan name -> prediction (absent = empty scan)."""
    scans = sample_scans(sample_dir)
    infos, per_class = [], {}
    for scan in scans:
        pred = predictions.get(scan.stem, {"boxes": np.zeros((0, 7), np.float32), "scores": np.zeros(0), "names": []})
        boxes, names = threshold_boxes(pred, min_score)
        for n in names:
            per_class[n] = per_class.get(n, 0) + 1
        infos.append(pi3det.make_info(scan.stem, platform_name, f"velodyne/{scan.name}",
                                      Boxes(boxes, np.asarray(names, dtype=str))))
    with atomic_path(out) as tmp:
        tmp.mkdir(parents=True)
        pi3det.write_infos(tmp / INFOS, infos)
        sidecar = {"sample_shard": str(sample_dir), "platform": platform_name, "scans": len(scans),
                   "score_threshold": float(min_score), "boxes": per_class, "labeler": labeler,
                   "seconds": round(seconds, 2)}
        (tmp / SIDECAR).write_text(json.dumps(sidecar, indent=1, default=str))
    return sidecar


def generated_records(sample_dirs: list[str | Path], box_dirs: list[str | Path]) -> tuple[list[dict], int]:
    """Training records of pseudo-boxed generated scans: (records, empty scans left out)."""
    from omnilidar.downstream.det.dataset import records_from_infos

    if len(sample_dirs) != len(box_dirs):
        raise InputError(None, f"{len(sample_dirs)} sample shards but {len(box_dirs)} pseudo-box shards")
    records, empty = [], 0
    for sdir, bdir in zip(sample_dirs, box_dirs):
        infos = pi3det.read_infos(Path(bdir) / INFOS)
        names = [s.stem for s in sample_scans(sdir)]
        if [str(i["frame_id"]) for i in infos] != names:
            raise InputError(bdir, f"does not match sample shard {sdir}: {len(names)} scans, {len(infos)} infos")
        for rec in records_from_infos(infos, sdir):
            if Path(rec["points"]).stat().st_size == 0:
                empty += 1
                continue
            records.append(rec)
    return records, empty
