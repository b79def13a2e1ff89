"""Dataset indexes: one JSON per dataset listing every scan (and label) per split.

Later stages read the index instead of walking dataset folders, so synthetic and
real datasets look the same to them. Indexing checks what is cheap to check
(files exist, sizes are whole records, label counts match scans) and fails with
one clear error naming the file otherwise.
"""

from __future__ import annotations

import json
from pathlib import Path

from omnilidar.errors import InputError
from omnilidar.io import kitti360, pi3det, semantickitti
from omnilidar.io.atomic import write_text_atomic
from omnilidar.manifest import listing_digest

DATASETS = ("semantickitti", "kitti360", "pi3det", "nuscenes")


def _check_points(path: Path, record_bytes: int) -> int:
    if not path.is_file():
        raise InputError(path, "scan file not found")
    size = path.stat().st_size
    if size == 0 or size % record_bytes:
        raise InputError(path, f"size {size} bytes is not a positive multiple of {record_bytes} "
                               f"({record_bytes // 4} float32 per point)")
    return size // record_bytes


def _check_label(path: Path, num_points: int, item_bytes: int = 4) -> None:
    if not path.is_file():
        raise InputError(path, "label file not found")
    count = path.stat().st_size / item_bytes
    if count != num_points:
        raise InputError(path, f"holds {count:g} labels but its scan has {num_points} points")


def _entry(points: Path, labels: Path | None, record_bytes=16, label_bytes=4, **extra) -> dict:
    n = _check_points(points, record_bytes)
    if labels is not None:
        _check_label(labels, n, label_bytes)
    return {"points": str(points), "labels": None if labels is None else str(labels), "num_points": n, **extra}


def index_semantickitti(root: Path, missing: list) -> dict:
    splits = {}
    for split, sequences in semantickitti.SPLITS.items():
        entries = []
        for seq in sequences:
            if not (root / "sequences" / seq).is_dir():
                missing.append(f"sequences/{seq}")
                continue
            for bin_path, label_path in semantickitti.sequence_paths(root, seq):
                if split != "test" and label_path is None:
                    raise InputError(bin_path, f"no label file for this {split} scan")
                entries.append(_entry(bin_path, label_path, sequence=seq, frame=bin_path.stem))
        splits[split] = entries
    return splits


def index_kitti360(root: Path, missing: list) -> dict:
    splits = {}
    for split, sequences in kitti360.SPLITS.items():
        entries = []
        for seq in sequences:
            if not kitti360.scan_path(root, seq, 0).parent.is_dir():
                missing.append(str(kitti360.scan_path(root, seq, 0).parent.relative_to(root)))
                continue
            for path in kitti360.sequence_paths(root, seq):
                entries.append(_entry(path, None, sequence=seq, frame=path.stem))
        splits[split] = entries
    return splits


def index_pi3det(root: Path, missing: list) -> dict:
    splits = {}
    for infos_path in sorted(root.glob("*/*_infos_*.pkl")):
        platform, _, split = infos_path.stem.partition("_infos_")
        entries = []
        for i, info in enumerate(pi3det.read_infos(infos_path)):
            points = root / info["point_clout_path"]
            labels = points.parent.parent / "labels" / f"{points.stem}.label"
            entries.append(_entry(points, labels if labels.exists() else None, platform=platform,
                                  frame=str(info["frame_id"]), infos=str(infos_path), info_index=i))
        splits[f"{platform}_{split}"] = entries
    return splits


def index_nuscenes(root: Path, missing: list) -> dict:
    # Layout written by the synthetic world (and accepted for real data converted
    # to it): <root>/<split>/samples/LIDAR_TOP/*.pcd.bin + lidarseg/<name>_lidarseg.bin.
    splits = {}
    for split_dir in sorted(p for p in root.iterdir() if (p / "samples" / "LIDAR_TOP").is_dir()):
        entries = []
        for points in sorted((split_dir / "samples" / "LIDAR_TOP").glob("*.pcd.bin")):
            name = points.name[: -len(".pcd.bin")]
            labels = split_dir / "lidarseg" / f"{name}_lidarseg.bin"
            entries.append(_entry(points, labels if labels.exists() else None, record_bytes=20,
                                  label_bytes=1, frame=name))
        splits[split_dir.name] = entries
    if not splits:
        raise InputError(root, "no <split>/samples/LIDAR_TOP folders found (see README: nuScenes layout)")
    return splits


def build_index(dataset: str, root: str | Path) -> dict:
    root = Path(root)
    if dataset not in DATASETS:
        raise InputError(None, f"unknown dataset {dataset!r}; known: {', '.join(DATASETS)}")
    if not root.is_dir():
        raise InputError(root, f"{dataset} root not found")
    # Official split members that are absent (a partial download, a small synthetic
    # set) are listed in the index rather than silently skipped.
    missing: list[str] = []
    splits = globals()[f"index_{dataset}"](root, missing)
    if not any(splits.values()):
        raise InputError(root, f"no {dataset} scans found under this root")
    # What the consumers' resumable state is keyed by: the exact content of shards
    # that carry a manifest (synthetic ones), a listing (names, sizes, times) otherwise.
    return {"dataset": dataset, "root": str(root), "root_digest": listing_digest(root), "splits": splits,
            "missing": missing}


def write_index(index: dict, path: str | Path) -> None:
    write_text_atomic(path, json.dumps(index, indent=1))


def read_index(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "dataset index not found (run the index_dataset rule)")
    return json.loads(path.read_text())
