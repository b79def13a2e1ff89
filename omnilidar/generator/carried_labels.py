"""True labels for SDEdited scans: each pixel keeps the label of its source scan's pixel.

A scan sampled with ``generator.sampling.strength`` < 1 starts from one of its domain's training
scans noised to t = strength; its pixels are the source's pixels, moved in range by the generator.
Giving each returned pixel the label of the source's nearest return in that pixel (0, unlabelled,
where the source had none) labels the edit without the labeler, which splits what the generator's
edits cost the student (these labels) from what they cost the labeler (its labels of the same
scans). Fresh samples (strength 1) have no source and get no such labels.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from omnilidar.errors import InputError


def source_files(range_file: Path) -> tuple[Path, Path]:
    """The points and labels of a domain training scan, beside its range image as build_domain
    writes them: ``SHARD/range/X.npz`` -> ``SHARD/velodyne/X.bin``, ``SHARD/labels/X.label``."""
    shard = range_file.parent.parent
    return shard / "velodyne" / f"{range_file.stem}.bin", shard / "labels" / f"{range_file.stem}.label"


def pixel_labels(points: np.ndarray, semantic: np.ndarray, instance: np.ndarray, spec) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) semantic and instance label of each pixel's nearest return (0 where none)."""
    from omnilidar.data.range_image import project

    winner = project(points, spec).point_index_img
    hit = winner >= 0
    sem = np.zeros(spec.shape, np.uint16)
    inst = np.zeros(spec.shape, np.uint16)
    sem[hit], inst[hit] = semantic[winner[hit]], instance[winner[hit]]
    return sem, inst


def carry_source_labels(samples: str | Path, out: str | Path, progress: bool = True) -> dict:
    """Label every scan of an SDEdited sample shard with its source's pixel labels; write
    ``out/labels/X.label`` (raw ids, like pseudo-label's) and ``out/sidecar.json``, atomically.
    Returns the sidecar: per scan the share of points that got a label."""
    from tqdm import tqdm

    from omnilidar.data.range_image import RangeImageSpec, decode
    from omnilidar.generator.sampling import SOURCES_FILE
    from omnilidar.io import semantickitti
    from omnilidar.io.atomic import atomic_path

    samples = Path(samples)
    doc_path = samples / SOURCES_FILE
    if not doc_path.is_file():
        raise InputError(samples, f"has no {SOURCES_FILE}: only scans sampled with generator.sampling.strength < 1 "
                                  "start from a training scan whose labels can be carried")
    doc = json.loads(doc_path.read_text())
    spec = RangeImageSpec(**doc["range_image"])
    scans = []
    with atomic_path(Path(out)) as tmp:
        (tmp / "labels").mkdir(parents=True)
        for name, source in tqdm(sorted(doc["scans"].items()), desc=f"carry labels {samples.name}",
                                 file=sys.stderr, disable=not progress, mininterval=2.0):
            points_file, labels_file = source_files(Path(source))
            if not labels_file.is_file():
                raise InputError(labels_file, f"source of sampled scan {name} has no label file to carry")
            points = semantickitti.read_points(points_file)
            sem, inst = pixel_labels(points, *semantickitti.read_label(labels_file, len(points)), spec)
            image_file = samples / "range" / f"{name}.npz"
            if not image_file.is_file():
                raise InputError(image_file, "sampled scan listed in sources.json is missing")
            valid = decode(np.load(image_file)["image"], spec)[2]  # sample_shard's own points, row-major
            count = (samples / "velodyne" / f"{name}.bin").stat().st_size // 16
            if count != int(valid.sum()):
                raise InputError(samples / "velodyne" / f"{name}.bin",
                                 f"holds {count} points but its range image decodes to {int(valid.sum())}")
            semantickitti.write_label(tmp / "labels" / f"{name}.label", sem[valid], inst[valid])
            scans.append({"name": name, "source": source, "points": count,
                          "labelled_share": float((sem[valid] > 0).mean()) if count else None})
        side = {"samples": str(samples), "strength": doc["strength"], "scans": scans}
        (tmp / "sidecar.json").write_text(json.dumps(side, indent=1))
    return side
