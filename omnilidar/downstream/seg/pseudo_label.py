"""Pseudo-labels for generated scans (and for real scans of a pool, to measure what
pseudo-labelling costs), and pairing them with their scans.

One pseudo-label shard per sample shard::

    OUT/labels/%06d.label    uint32 raw SemanticKITTI ids (train ids through LEARNING_MAP_INV)
    OUT/confidence/%06d.bin  uint8 per point: the labeler's softmax probability of that label x 255
    OUT/sidecar.json         sample shard, scan names and point counts, labeler

named like the sample shard's ``velodyne/%06d.bin``. A generated scan with no
points gets an empty label file (its count matches). When a GDA run reads a
pseudo-label shard, :func:`generated_records` checks it against its sample
shard (same scan names, one label per point) and fails with one clear error
otherwise.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.data.subsets import read_subset
from omnilidar.downstream.seg.dataset import CONFIDENCE, records_from_entries
from omnilidar.downstream.seg.evaluate import predict_points
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path
from omnilidar.io.json_file import read_json
from omnilidar.metrics.segmentation import ConfusionMatrix

SIDECAR = "sidecar.json"
def sample_scans(sample_dir: str | Path) -> list[Path]:
    """The ``velodyne/*.bin`` scans of a sample shard, sorted by name."""
    velo = Path(sample_dir) / "velodyne"
    if not velo.is_dir():
        raise InputError(sample_dir, "sample shard has no velodyne/ folder")
    scans = sorted(velo.glob("*.bin"))
    if not scans:
        raise InputError(velo, "sample shard holds no .bin scans")
    return scans


@torch.no_grad()
def pseudo_label_shard(model: torch.nn.Module, payload: dict, sample_dir: str | Path, out: str | Path,
                       batch_size: int = 2) -> dict:
    """Label every scan of a sample shard; write the pseudo-label shard ``out`` atomically."""
    scans = [(p.stem, p, None) for p in sample_scans(sample_dir)]
    return _pseudo_label(model, payload, scans, out, batch_size, {"sample_shard": str(sample_dir)})


@torch.no_grad()
def pseudo_label_pool(model: torch.nn.Module, payload: dict, pool_path: str | Path, out: str | Path,
                      batch_size: int = 2) -> dict:
    """Label the real scans of a pool (``make-subset --exclude``): ``labels/%06d.label`` for its k-th
    scan, and, where the scans have true labels, the pseudo-labels' accuracy against them."""
    pool = read_subset(pool_path)
    if pool["dataset"] != "semantickitti":
        raise InputError(pool_path, f"the labeler labels SemanticKITTI scans, not {pool['dataset']}")
    scans = [(f"{k:06d}", Path(e["points"]), e.get("labels")) for k, e in enumerate(pool["entries"])]
    return _pseudo_label(model, payload, scans, out, batch_size, {"pool": str(pool_path)})


def _pseudo_label(model, payload: dict, scans: list[tuple], out: str | Path, batch_size: int, source: dict) -> dict:
    """Write ``labels/<name>.label`` for each ``(name, scan path, true label path or None)`` and the sidecar."""
    space = get_label_space(payload["label_space"])
    started = time.time()
    records = []
    hist = np.zeros(space.num_ids, np.int64)
    truth = ConfusionMatrix(space.num_ids) if any(t for _, _, t in scans) else None
    with atomic_path(out) as tmp:
        (tmp / "labels").mkdir(parents=True)
        (tmp / CONFIDENCE).mkdir()
        for start in range(0, len(scans), batch_size):
            chunk = scans[start:start + batch_size]
            clouds = [semantickitti.read_points(path) for _, path, _ in chunk]
            nonempty = [i for i, c in enumerate(clouds) if len(c)]
            preds = dict(zip(nonempty, predict_points(
                model, [clouds[i] for i in nonempty], payload["voxel_size"], space.num_ids,
                [chunk[i][1] for i in nonempty], confidence=True))) if nonempty else {}
            for i, (name, path, truth_path) in enumerate(chunk):
                train_ids, prob = preds.get(i, (np.zeros(0, np.uint8), np.zeros(0, np.float32)))
                hist += np.bincount(train_ids, minlength=space.num_ids)
                semantickitti.write_label(tmp / "labels" / f"{name}.label", semantickitti.to_raw_ids(train_ids))
                np.round(prob * 255).astype(np.uint8).tofile(tmp / CONFIDENCE / f"{name}.bin")
                record = {"name": name, "num_points": len(clouds[i])}
                if truth_path:
                    semantic, _ = semantickitti.read_label(truth_path, num_points=len(clouds[i]))
                    truth.update(semantickitti.to_train_ids(semantic), train_ids, truth_path)
                    record["source"] = str(path)
                records.append(record)
            print(f"pseudo-labelled {min(start + batch_size, len(scans))}/{len(scans)} scans", flush=True)
        sidecar = {
            **source,
            "scans": records,
            "labeler": {"model": payload["model"], "voxel_size": payload["voxel_size"],
                        "train": payload.get("train", {})},
            "class_histogram": {n: int(c) for n, c in zip(("ignore", *space.class_names), hist)},
            # How right the labels are where the truth is known (the real scans of a pool).
            "accuracy_against_truth": None if truth is None else truth.result().as_dict(list(space.class_names)),
            "seconds": round(time.time() - started, 2),
        }
        (tmp / SIDECAR).write_text(json.dumps(sidecar, indent=1, default=str))
    return sidecar


def pool_records(pool_path: str | Path, label_dir: str | Path | None) -> list[dict]:
    """Training records of a pool's real scans: with their true labels (``label_dir`` None) or with
    the pseudo-labels of :func:`pseudo_label_pool` in ``label_dir`` (checked against the pool)."""
    pool = read_subset(pool_path)
    records = records_from_entries(pool["entries"], pool["dataset"])
    if label_dir is None:
        return records
    side = read_json(Path(label_dir) / SIDECAR, "pseudo-label folder has no sidecar.json (run pseudo-label --pool)")
    if side.get("pool") is None or len(side["scans"]) != len(records):
        raise InputError(label_dir, f"was not made from a pool of {len(records)} scans like {pool_path}")
    for k, (rec, scan) in enumerate(zip(records, side["scans"])):
        if scan.get("source") != rec["points"]:
            raise InputError(label_dir, f"scan {k} was labelled from {scan.get('source')}, the pool holds {rec['points']}")
        labels = Path(label_dir) / "labels" / f"{k:06d}.label"
        if not labels.is_file():
            raise InputError(labels, "pseudo-label file missing")
        rec["labels"], rec["pseudo"] = str(labels), True
    return records


def generated_records(sample_dirs: list[str | Path], label_dirs: list[str | Path],
                      limit: int | None = None) -> tuple[list[dict], int]:
    """Training records of generated scans: (records, number of empty scans left out).

    Shards are paired in order; each pseudo-label shard must hold exactly one
    label file per scan of its sample shard with one label per point.
    ``limit`` keeps only the first ``limit`` scans (shards in the order given,
    scans in name order; empty scans count towards it) and fails when the
    shards hold fewer; shards after the limit are not read.
    """
    if len(sample_dirs) != len(label_dirs):
        raise InputError(None, f"{len(sample_dirs)} sample shards but {len(label_dirs)} pseudo-label shards")
    if limit is not None and limit < 1:
        raise InputError(None, f"the number of generated scans to use must be >= 1, got {limit}")
    records, empty = [], 0
    for sdir, ldir in zip(sample_dirs, label_dirs):
        if limit is not None and len(records) + empty >= limit:
            break
        scans = sample_scans(sdir)
        labels_dir = Path(ldir) / "labels"
        if not labels_dir.is_dir():
            raise InputError(ldir, "pseudo-label shard has no labels/ folder")
        labels = {p.stem: p for p in labels_dir.glob("*.label")}
        names = [s.stem for s in scans]
        if sorted(labels) != names:
            missing = sorted(set(names) - set(labels))
            extra = sorted(set(labels) - set(names))
            raise InputError(ldir, f"does not match sample shard {sdir}: {len(scans)} scans, {len(labels)} labels"
                                   + (f", first scan without label {missing[0]}" if missing else "")
                                   + (f", first label without scan {extra[0]}" if extra else ""))
        if limit is not None:
            scans = scans[: limit - len(records) - empty]
        for scan in scans:
            n = scan.stat().st_size // 16
            if scan.stat().st_size % 16:
                raise InputError(scan, "size is not a multiple of 16 bytes (float32 x,y,z,intensity)")
            count = labels[scan.stem].stat().st_size / 4
            if count != n:
                raise InputError(labels[scan.stem], f"holds {count:g} labels but sample scan {scan} has {n} points "
                                                    f"(pseudo-label shard does not match its sample shard)")
            if n == 0:
                empty += 1
                continue
            records.append({"points": str(scan), "labels": str(labels[scan.stem]), "format": "semantickitti",
                            "pseudo": True})
    if limit is not None and len(records) + empty < limit:
        raise InputError(sample_dirs[-1] if sample_dirs else None,
                         f"the generated shards hold {len(records) + empty} scans, fewer than the {limit} asked for")
    return records, empty
