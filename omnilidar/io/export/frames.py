"""What an export reads: sample shards with their pseudo-labels or pseudo-boxes, through their manifests.

A sample shard (``omnilidar sample``) holds ``velodyne/<name>.bin``; a pseudo-label
shard (``omnilidar pseudo-label``) ``labels/<name>.label`` in raw SemanticKITTI ids;
a pseudo-box shard (``omnilidar pseudo-box``) ``infos.pkl``, Pi3DET infos whose
``frame_id`` is the scan name. Every shard is a finished stage output, so it carries
``MANIFEST.sha256``: the scans are the ones its manifest lists, and every file the
export reads is checked against its digest there (a shard edited after it was
written is an error, not a silent mix). Shards are paired in the order given.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from omnilidar.errors import InputError
from omnilidar.geometry.points_in_boxes import points_in_boxes_mask
from omnilidar.io import pi3det, semantickitti
from omnilidar.manifest import MANIFEST_NAME

BOX_INFOS = "infos.pkl"  # omnilidar.downstream.det.pseudo_boxes.INFOS
POINT_COLUMNS = 4  # float32 x, y, z, intensity


@dataclass(frozen=True)
class SourceFrame:
    """One generated scan and where its labels and boxes come from."""

    name: str
    points: Path
    points_sha256: str
    labels: Path | None = None
    labels_sha256: str | None = None
    boxes: np.ndarray | None = None  # (M, 7) float32 x, y, z_center, dx, dy, dz, heading
    box_names: tuple[str, ...] | None = None


def read_manifest(shard: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of a finished shard; an error when it has none."""
    if not shard.is_dir():
        raise InputError(shard, "no such shard directory")
    manifest = shard / MANIFEST_NAME
    if not manifest.is_file():
        raise InputError(shard, f"has no {MANIFEST_NAME}: not a finished stage output")
    entries = {}
    for lineno, line in enumerate(manifest.read_text().splitlines(), 1):
        digest, sep, rel = line.partition("  ")
        if not sep or len(digest) != 64 or not rel:
            raise InputError(manifest, f"line {lineno}: expected '<sha256>  <relative path>'")
        entries[rel] = digest
    return entries


def read_checked(path: Path, expected: str) -> bytes:
    """The bytes of ``path``, which must hash to the digest its shard's manifest lists."""
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != expected:
        raise InputError(path, f"content differs from its shard's {MANIFEST_NAME} (changed after it was written)")
    return data


def _listed(shard: Path, manifest: dict[str, str], folder: str, suffix: str) -> dict[str, str]:
    """``{stem: relative path}`` of the manifest's ``folder/*suffix`` files, checked against the disk."""
    listed = {Path(rel).stem: rel for rel in manifest if rel.startswith(f"{folder}/") and rel.endswith(suffix)
              and rel.count("/") == 1}
    on_disk = {p.stem for p in (shard / folder).glob(f"*{suffix}")} if (shard / folder).is_dir() else set()
    extra = sorted(on_disk - set(listed))
    if extra:
        raise InputError(shard / folder / f"{extra[0]}{suffix}", f"is not in {MANIFEST_NAME} (added after the shard was written)")
    missing = sorted(set(listed) - on_disk)
    if missing:
        raise InputError(shard / folder / f"{missing[0]}{suffix}", f"is listed in {MANIFEST_NAME} but missing")
    return listed


def _sample_frames(shard: Path) -> list[SourceFrame]:
    manifest = read_manifest(shard)
    scans = _listed(shard, manifest, "velodyne", ".bin")
    if not scans:
        raise InputError(shard, f"{MANIFEST_NAME} lists no velodyne/*.bin scan: not a sample shard")
    return [SourceFrame(name, shard / scans[name], manifest[scans[name]]) for name in sorted(scans)]


def _with_labels(frames: list[SourceFrame], sample_shard: Path, label_shard: Path) -> list[SourceFrame]:
    manifest = read_manifest(label_shard)
    labels = _listed(label_shard, manifest, "labels", ".label")
    names = [f.name for f in frames]
    if sorted(labels) != names:
        missing = sorted(set(names) - set(labels))
        detail = f"no label for scan {missing[0]}" if missing else f"label {sorted(set(labels) - set(names))[0]} has no scan"
        raise InputError(label_shard, f"does not match sample shard {sample_shard}: {len(names)} scans, "
                                      f"{len(labels)} labels ({detail})")
    return [SourceFrame(f.name, f.points, f.points_sha256, label_shard / labels[f.name], manifest[labels[f.name]])
            for f in frames]


def _with_boxes(frames: list[SourceFrame], sample_shard: Path, box_shard: Path) -> list[SourceFrame]:
    manifest = read_manifest(box_shard)
    if BOX_INFOS not in manifest:
        raise InputError(box_shard, f"{MANIFEST_NAME} lists no {BOX_INFOS}: not a pseudo-box shard")
    read_checked(box_shard / BOX_INFOS, manifest[BOX_INFOS])
    infos = pi3det.read_infos(box_shard / BOX_INFOS)
    ids = [str(i["frame_id"]) for i in infos]
    if ids != [f.name for f in frames]:
        raise InputError(box_shard / BOX_INFOS, f"does not match sample shard {sample_shard}: {len(frames)} scans, "
                                                f"{len(infos)} infos (frame_id must be the scan names in order)")
    out = []
    for frame, info in zip(frames, infos):
        if info[pi3det.POINT_PATH_KEY] != f"velodyne/{frame.name}.bin":
            raise InputError(box_shard / BOX_INFOS, f"info {frame.name!r} points to {info[pi3det.POINT_PATH_KEY]!r}, "
                                                    f"not velodyne/{frame.name}.bin of its sample shard")
        annos = info.get("annos", {"gt_boxes_lidar": np.zeros((0, 7), np.float32), "gt_names": np.zeros(0, str)})
        out.append(SourceFrame(frame.name, frame.points, frame.points_sha256, frame.labels, frame.labels_sha256,
                               np.asarray(annos["gt_boxes_lidar"], np.float32).reshape(-1, 7),
                               tuple(str(n) for n in annos["gt_names"])))
    return out


def _pairs(what: str, shards: list[Path] | None, samples: list[Path]) -> list[Path | None]:
    if not shards:
        return [None] * len(samples)
    if len(shards) != len(samples):
        raise InputError(None, f"{len(samples)} sample shards but {len(shards)} {what} shards (pair them in order)")
    return shards


def collect_frames(samples: list[str | Path], labels: list[str | Path] | None = None,
                   boxes: list[str | Path] | None = None) -> list[SourceFrame]:
    """Every scan of the sample shards (shard order, then name order) with its labels and boxes."""
    samples = [Path(s) for s in samples]
    if not samples:
        raise InputError(None, "no sample shard given")
    seen = {}
    for shard in samples:
        key = shard.resolve()
        if key in seen:
            raise InputError(shard, f"given twice (also as {seen[key]})")
        seen[key] = shard
    label_shards = _pairs("pseudo-label", [Path(p) for p in labels or []], samples)
    box_shards = _pairs("pseudo-box", [Path(p) for p in boxes or []], samples)
    frames = []
    for shard, lshard, bshard in zip(samples, label_shards, box_shards):
        part = _sample_frames(shard)
        if lshard is not None:
            part = _with_labels(part, shard, lshard)
        if bshard is not None:
            part = _with_boxes(part, shard, bshard)
        frames.extend(part)
    return frames


def load_points(frame: SourceFrame) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity, checked against the manifest, finite."""
    data = read_checked(frame.points, frame.points_sha256)
    if len(data) % (4 * POINT_COLUMNS):
        raise InputError(frame.points, f"size {len(data)} bytes is not a multiple of 16 (4 float32 per point)")
    points = np.frombuffer(data, np.float32).reshape(-1, POINT_COLUMNS).copy()
    if not np.isfinite(points).all():
        raise InputError(frame.points, "holds NaN or infinite values")
    return points


def load_labels(frame: SourceFrame, num_points: int) -> np.ndarray:
    """(N,) uint32 raw SemanticKITTI labels (semantic | instance << 16), one per point, known ids only."""
    data = read_checked(frame.labels, frame.labels_sha256)
    if len(data) % 4:
        raise InputError(frame.labels, f"size {len(data)} bytes is not a multiple of 4 (uint32 per point)")
    labels = np.frombuffer(data, np.uint32).copy()
    if len(labels) != num_points:
        raise InputError(frame.labels, f"holds {len(labels)} labels but scan {frame.points} has {num_points} points")
    unknown = sorted(set(np.unique(labels & 0xFFFF).tolist()) - set(semantickitti.LEARNING_MAP))
    if unknown:
        raise InputError(frame.labels, f"semantic ids {unknown[:5]} are not SemanticKITTI raw ids")
    return labels


def inside_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N, M) bool: which points lie in which box (faces count as inside; OpenPCDet's
    points_in_boxes_cpu and mmdet3d's points_in_rbbox agree up to points on the faces)."""
    if len(boxes) == 0:
        return np.zeros((len(points), 0), bool)
    return points_in_boxes_mask(torch.from_numpy(points[:, :3]), torch.from_numpy(np.asarray(boxes, np.float32))).numpy()


def assign_splits(count: int, val_every: int) -> list[str]:
    """'train' or 'val' per exported frame: with ``val_every`` k > 0, the first frame and every
    k-th after it go to val (as ``omnilidar split-pi3det`` picks sequences); 0 puts all in train."""
    if val_every < 0:
        raise InputError(None, f"--val-every must be >= 0, got {val_every}")
    return ["val" if val_every and i % val_every == 0 else "train" for i in range(count)]


@dataclass(frozen=True)
class ExportFrame:
    """A frame as exported: its new name (``%06d``, numbered over the export), split and source,
    with ``shift`` (x, y, z) added to its points and box centres (OpenPCDet's SHIFT_COOR)."""

    index: int
    split: str
    source: SourceFrame
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    renames: tuple[tuple[str, str], ...] = ()  # (our class name, exported name)

    @property
    def name(self) -> str:
        return f"{self.index:06d}"

    def points(self) -> np.ndarray:
        points = load_points(self.source)
        points[:, :3] += np.asarray(self.shift, np.float32)
        return points

    @property
    def boxes(self) -> np.ndarray:
        boxes = np.asarray(self.source.boxes, np.float32).reshape(-1, 7).copy()
        boxes[:, :3] += np.asarray(self.shift, np.float32)
        return boxes

    @property
    def box_names(self) -> tuple[str, ...]:
        renames = dict(self.renames)
        return tuple(renames.get(n, n) for n in self.source.box_names)


def parse_renames(pairs: list[str] | None) -> tuple[tuple[str, str], ...]:
    """``["Car=Vehicle", ...]`` -> ((Car, Vehicle), ...); the old names must be our classes."""
    out = []
    for pair in pairs or []:
        old, sep, new = pair.partition("=")
        if not sep or old not in pi3det.CLASSES or not new or any(c.isspace() for c in new):
            raise InputError(None, f"--rename-class {pair!r}: expected OLD=NEW with OLD one of "
                                   f"{', '.join(pi3det.CLASSES)} and NEW one word")
        out.append((old, new))
    if len({old for old, _ in out}) != len(out):
        raise InputError(None, "--rename-class names a class twice")
    return tuple(out)


def plan_export(frames: list[SourceFrame], val_every: int, shift=(0.0, 0.0, 0.0),
                renames: tuple[tuple[str, str], ...] = ()) -> tuple[list[ExportFrame], list[SourceFrame]]:
    """Number the frames that have points and split them; returns (exported, empty scans left out).

    Generated scans can come out empty; neither OpenPCDet nor mmdet3d can train on an
    empty cloud, so they are left out and listed in the export's ``export.json``.
    """
    kept = [f for f in frames if f.points.stat().st_size > 0]
    empty = [f for f in frames if f.points.stat().st_size == 0]
    if not kept:
        raise InputError(frames[0].points.parent if frames else None, "every scan of the sample shards is empty")
    shift = tuple(float(v) for v in shift)
    if len(shift) != 3 or not np.isfinite(shift).all():
        raise InputError(None, f"--shift-coor needs three finite numbers, got {shift}")
    splits = assign_splits(len(kept), val_every)
    return [ExportFrame(i, s, f, shift, renames) for i, (s, f) in enumerate(zip(splits, kept))], empty


def split_names(planned: list[ExportFrame]) -> dict[str, list[ExportFrame]]:
    """Frames per split, 'train' and 'val' always present (possibly empty), in export order."""
    out = {"train": [], "val": []}
    for frame in planned:
        out[frame.split].append(frame)
    return out
