"""Scan lists -> augmented, voxelised batches for segmentation training and evaluation.

A *record* names one labelled scan: ``{"points": path, "labels": path, "format": f}``
with ``f`` one of

* ``semantickitti``: KITTI ``.bin`` (x, y, z, remission 0..1) and a uint32
  ``.label`` of RAW SemanticKITTI ids (real scans and pseudo-labelled samples);
* ``nuscenes``: ``.pcd.bin`` (x, y, z, intensity 0..255, ring) and a uint8
  lidarseg file of nuScenes general classes.

Scans are read into 4 features x, y, z, intensity with intensity in 0..1 for
both formats (nuScenes intensities are divided by 255), and labels are mapped
to the train ids of the run's label space (:mod:`.label_spaces`).

Training draws come from :class:`MixedBatchSampler`, an endless, deterministic
stream of batches over real and generated scans. Each drawn scan carries its
draw number, and its augmentation (rotation about z ~ U[0, 2 pi), isotropic
scale ~ U[lo, hi]) and voxel-cap subset come from a generator seeded by
(seed, draw number): a batch's content does not depend on worker processes,
batch composition or resumption.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from omnilidar.downstream.seg.label_spaces import (
    LabelSpace,
    nuscenes_train_ids,
    semantickitti_to_nuscenes,
)
from omnilidar.downstream.seg.lasermix import laser_mix
from omnilidar.segnets.voxelize import SegBatch, collate
from omnilidar.downstream.schedule import epoch_length, generated_per_epoch
from omnilidar.errors import InputError
from omnilidar.io import nuscenes, semantickitti

FORMATS = ("semantickitti", "nuscenes")
_BYTES_PER_POINT = {"semantickitti": 16, "nuscenes": 20}


def draw_rng(seed: int, draw: int, purpose: int = 0) -> np.random.Generator:
    """The generator of one training draw: purpose 0 augmentation, 1 voxel cap, 2 point cap,
    3 LaserMix partner and bands."""
    return np.random.default_rng([int(seed), 0x5E6, int(purpose), int(draw)])


def records_from_entries(entries: list[dict], fmt: str) -> list[dict]:
    """Records of dataset-index (or subset) entries; every entry needs a label file."""
    if fmt not in FORMATS:
        raise InputError(None, f"unknown scan format {fmt!r}; known: {', '.join(FORMATS)}")
    out = []
    for e in entries:
        if not e.get("labels"):
            raise InputError(e.get("points"), "scan has no label file")
        out.append({"points": str(e["points"]), "labels": str(e["labels"]), "format": fmt})
    return out


def num_points(record: dict) -> int:
    """Point count of a record's scan from its file size (no read)."""
    path = Path(record["points"])
    if not path.is_file():
        raise InputError(path, "scan file not found")
    size, rec = path.stat().st_size, _BYTES_PER_POINT[record["format"]]
    if size % rec:
        raise InputError(path, f"size {size} bytes is not a multiple of {rec}")
    return size // rec


def read_points(record: dict) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity in 0..1 of a record's scan."""
    fmt = record["format"]
    if fmt == "semantickitti":
        return semantickitti.read_points(record["points"])
    if fmt == "nuscenes":
        raw = nuscenes.read_points(record["points"])
        pts = np.ascontiguousarray(raw[:, :4])
        pts[:, 3] = np.clip(pts[:, 3] / nuscenes.INTENSITY_MAX, 0.0, 1.0)
        return pts
    raise InputError(record["points"], f"unknown scan format {fmt!r}")


def read_train_ids(record: dict, n: int, space: LabelSpace) -> np.ndarray:
    """Per-point train ids (uint8, 0 = ignore) of a record in label space ``space``."""
    path = Path(record["labels"])
    if not path.is_file():
        raise InputError(path, f"label file not found (scan {record['points']})")
    fmt = record["format"]
    if fmt == "semantickitti":
        semantic, _ = semantickitti.read_label(path, num_points=n)
        ids = semantickitti.to_train_ids(semantic)
        if space.name == "semantickitti":
            return ids
        if space.name == "nuscenes":
            return semantickitti_to_nuscenes(ids)
    elif fmt == "nuscenes":
        if space.name == "nuscenes":
            return nuscenes_train_ids(nuscenes.read_lidarseg(path, n))
    raise InputError(path, f"{fmt} labels cannot be mapped to the {space.name} label space")


def read_record(record: dict, space: LabelSpace) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 4) and train ids (N,) of one labelled scan."""
    points = read_points(record)
    return points, read_train_ids(record, len(points), space)


CONFIDENCE = "confidence"


def confidence_file(label_file: str | Path) -> Path:
    """The confidence file beside a pseudo-label file (``labels/X.label`` -> ``confidence/X.bin``)."""
    label_file = Path(label_file)
    return label_file.parent.parent / CONFIDENCE / f"{label_file.stem}.bin"


def read_confidence(label_file: str | Path, num_points: int) -> np.ndarray | None:
    """Per-point labeler confidence (0..1) of a pseudo-label file, None when none was written."""
    path = confidence_file(label_file)
    if not path.is_file():
        return None
    conf = np.fromfile(path, np.uint8)
    if len(conf) != num_points:
        raise InputError(path, f"holds {len(conf)} confidences for {num_points} points")
    return conf.astype(np.float32) / 255.0


def confident_labels(record: dict, labels: np.ndarray, threshold: float) -> np.ndarray:
    """``labels`` with the points whose pseudo-label confidence is below ``threshold`` set to ignore."""
    conf = read_confidence(record["labels"], len(labels))
    if conf is None:
        raise InputError(record["labels"], "pseudo-labels have no confidences (made by an older pseudo-label run)")
    return np.where(conf >= threshold, labels, 0).astype(labels.dtype)


def augment(points: np.ndarray, rng: np.random.Generator, rotation: bool, scale: tuple[float, float],
            range_jitter: float = 0.0) -> np.ndarray:
    """Rotate about z by U[0, 2 pi) (if ``rotation``) and scale x, y, z by U[lo, hi]; with
    ``range_jitter`` > 0 first move each point along its ray by :func:`jitter_ranges` of a size
    drawn from U[0, range_jitter] (drawn after the rotation and scale, so 0 changes nothing)."""
    factor = float(rng.uniform(scale[0], scale[1])) if scale[1] > scale[0] else float(scale[0])
    theta = float(rng.uniform(0.0, 2.0 * math.pi)) if rotation else None
    if range_jitter > 0:
        points = jitter_ranges(points, float(rng.uniform(0.0, range_jitter)), rng)
    out = points.copy()
    if theta is not None:
        c, s = math.cos(theta), math.sin(theta)
        rot = np.array([[c, -s], [s, c]], np.float64) * factor
        out[:, :2] = (points[:, :2].astype(np.float64) @ rot.T).astype(np.float32)
        out[:, 2] = points[:, 2] * np.float32(factor)
    else:
        out[:, :3] = points[:, :3] * np.float32(factor)
    return out


def jitter_ranges(points: np.ndarray, size: float, rng: np.random.Generator) -> np.ndarray:
    """``points`` (sensor frame) with each point moved along its ray so that ln(range + 1) changes
    by ``size`` * N(0, 1): the relative range error a generator leaves (sampling.range_noise on the
    encoded log-range is this on ln(range + 1), scaled by ln(max_range + 1) / 2)."""
    xyz = points[:, :3].astype(np.float64)
    dist = np.linalg.norm(xyz, axis=1)
    moved = (dist + 1.0) * np.exp(size * rng.standard_normal(len(dist))) - 1.0
    ratio = np.divide(np.maximum(moved, 0.0), dist, out=np.ones_like(dist), where=dist > 0)
    out = points.copy()
    out[:, :3] = (xyz * ratio[:, None]).astype(points.dtype)
    return out


class SegScanDataset(torch.utils.data.Dataset):
    """Labelled scans, indexed by ``(draw, i)`` (training) or ``i`` (evaluation).

    ``max_points`` caps the points of a training draw (random subset, purpose 2
    of :func:`draw_rng`); evaluation items are never capped. With ``augmentation`` (dict with ``rotation`` and ``scale``) a ``(draw, i)``
    item is augmented with :func:`draw_rng` ``(seed, draw)``. With ``lasermix_from`` = R, a
    training draw of record i >= R is LaserMix-ed (:mod:`.lasermix`) with one of the records
    0..R-1, drawn with purpose 3, before the point cap and augmentation. With
    ``min_confidence`` > 0, points of pseudo-labelled records (``"pseudo": True``) whose labeler
    confidence is below it are ignored in training (label 0).
    """

    def __init__(self, records: list[dict], space: LabelSpace, augmentation: dict | None = None, seed: int = 0,
                 max_points: int | None = None, lasermix_from: int | None = None, min_confidence: float = 0.0):
        self.records = list(records)
        self.space = space
        self.augmentation = augmentation
        self.seed = int(seed)
        self.max_points = max_points
        self.lasermix_from = lasermix_from
        self.min_confidence = float(min_confidence)

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, key) -> dict:
        draw, i = key if isinstance(key, tuple) else (None, key)
        rec = self.records[i]
        points, labels = read_record(rec, self.space)
        if self.min_confidence > 0 and draw is not None and rec.get("pseudo"):
            labels = confident_labels(rec, labels, self.min_confidence)
        if self.lasermix_from and draw is not None and i >= self.lasermix_from:
            rng = draw_rng(self.seed, draw, purpose=3)
            partner = read_record(self.records[int(rng.integers(self.lasermix_from))], self.space)
            points, labels = laser_mix((points, labels), partner, rng)
        if self.max_points and draw is not None and len(points) > self.max_points:
            # Training-time point cap (CPU budget): a random subset, in file order.
            keep = np.sort(draw_rng(self.seed, draw, purpose=2).choice(len(points), self.max_points, replace=False))
            points, labels = points[keep], labels[keep]
        if self.augmentation is not None and draw is not None:
            aug = self.augmentation
            points = augment(points, draw_rng(self.seed, draw), bool(aug["rotation"]), tuple(aug["scale"]),
                             float(aug.get("range_jitter", 0.0)))
        return {"points": points, "labels": labels, "path": rec["points"], "draw": draw, "index": i}


@dataclass
class SegCollate:
    """Collate function: items -> ``{"batch": SegBatch}`` (``None`` for skipped batches).

    The voxel cap of a training batch draws from the generator of its first
    item's draw number, so it is reproducible.
    """

    num_ids: int
    voxel_size: float
    max_voxels: int | None = None
    seed: int = 0

    def __call__(self, items: list[dict]) -> dict:
        if not items:
            return {"batch": None}  # fast-forwarded batch on resume
        draw = items[0]["draw"]
        rng = draw_rng(self.seed, draw, purpose=1) if draw is not None else None
        batch = collate(
            [it["points"] for it in items], [it["labels"] for it in items], num_classes=self.num_ids,
            voxel_size=self.voxel_size, max_voxels=self.max_voxels if rng is not None else None, rng=rng,
            paths=[it["path"] for it in items],
        )
        return {"batch": batch}


def epoch_plan(num_real: int, num_generated: int, mixing: dict, epoch: int, seed: int) -> np.ndarray:
    """Dataset indices of one epoch (real 0..R-1, generated R..R+G-1), shuffled.

    ``mixing["mode"]``: ``concat`` = every real and every generated scan once;
    ``ratio`` = every real scan once plus enough generated scans (cycling through
    a fixed permutation across epochs) that they make up ``generated_share`` of
    the epoch.
    """
    rng = np.random.default_rng([int(seed), 0xE70C, int(epoch)])
    real = np.arange(num_real)
    count = generated_per_epoch(num_real, num_generated, mixing)
    if mixing["mode"] == "ratio" and count:
        order = np.random.default_rng([int(seed), 0x6E4]).permutation(num_generated)
        gen = num_real + order[(epoch * count + np.arange(count)) % num_generated]
    else:
        gen = num_real + np.arange(count)
    return rng.permutation(np.concatenate([real, gen]))


class MixedBatchSampler(torch.utils.data.Sampler):
    """Endless batches of ``(draw, index)`` keys over the epochs of :func:`epoch_plan`.

    Batches never straddle epochs' boundaries in a way that repeats a scan within
    a batch: the stream is the concatenation of epoch plans, cut into batches.
    The first ``skip`` batches are yielded empty (resume fast-forward without I/O).
    """

    def __init__(self, num_real: int, num_generated: int, mixing: dict, batch_size: int, seed: int,
                 skip: int = 0):
        if num_real + num_generated == 0:
            raise InputError(None, "no training scans")
        self.num_real, self.num_generated = num_real, num_generated
        self.mixing, self.batch_size, self.seed, self.skip = mixing, int(batch_size), int(seed), int(skip)

    def _stream(self) -> Iterator[tuple[int, int]]:
        draw, epoch = 0, 0
        while True:
            for i in epoch_plan(self.num_real, self.num_generated, self.mixing, epoch, self.seed):
                yield draw, int(i)
                draw += 1
            epoch += 1

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        stream = self._stream()
        number = 0
        while True:
            batch = [next(stream) for _ in range(self.batch_size)]
            yield [] if number < self.skip else batch
            number += 1

    def __len__(self) -> int:  # one epoch's batches (mmengine only logs it)
        return max(1, math.ceil(epoch_length(self.num_real, self.num_generated, self.mixing) / self.batch_size))


def eval_batches(dataset: SegScanDataset, batch_size: int, voxel_size: float) -> Iterator[tuple[list[int], SegBatch]]:
    """(indices, batch) over a dataset in order, without augmentation or voxel cap."""
    coll = SegCollate(dataset.space.num_ids, voxel_size)
    for start in range(0, len(dataset), batch_size):
        idx = list(range(start, min(start + batch_size, len(dataset))))
        yield idx, coll([dataset[i] for i in idx])["batch"]
