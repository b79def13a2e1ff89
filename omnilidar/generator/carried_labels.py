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


def carry_source_labels(samples: str | Path, out: str | Path, progress: bool = True) -> dict:
    """Label every scan of an SDEdited sample shard with its source's pixel labels; write
    ``out/labels/X.label`` (raw ids, like pseudo-label's) and ``out/sidecar.json``, atomically.
    Returns the sidecar: per scan the share of points that got a label."""
    from tqdm import tqdm

    from omnilidar.data.range_image import RangeImageSpec, decode, project
    from omnilidar.generator.sampling import read_sources
    from omnilidar.io import semantickitti
    from omnilidar.io.atomic import atomic_path

    samples = Path(samples)
    doc, edits = read_sources(samples)
    spec = RangeImageSpec(**doc["range_image"])
    scans = []
    with atomic_path(Path(out)) as tmp:
        (tmp / "labels").mkdir(parents=True)
        for name, image_file, source in tqdm(edits, desc=f"carry labels {samples.name}", file=sys.stderr,
                                             disable=not progress, mininterval=2.0):
            points_file, labels_file = source_files(source)
            if not labels_file.is_file():
                raise InputError(labels_file, f"source of sampled scan {name} has no label file to carry")
            points = semantickitti.read_points(points_file)
            proj = project(points, spec)  # each pixel's nearest return carries its labels
            sem, inst = (proj.per_pixel(v) for v in semantickitti.read_label(labels_file, len(points)))
            valid = decode(np.load(image_file)["image"], spec)[2]  # sample_shard's own points, row-major
            count = (samples / "velodyne" / f"{name}.bin").stat().st_size // 16
            if count != int(valid.sum()):
                raise InputError(samples / "velodyne" / f"{name}.bin",
                                 f"holds {count} points but its range image decodes to {int(valid.sum())}")
            semantickitti.write_label(tmp / "labels" / f"{name}.label", sem[valid], inst[valid])
            scans.append({"name": name, "source": str(source), "points": count,
                          "labelled_share": float((sem[valid] > 0).mean()) if count else None})
        side = {"samples": str(samples), "strength": doc["strength"], "scans": scans}
        (tmp / "sidecar.json").write_text(json.dumps(side, indent=1))
    return side
