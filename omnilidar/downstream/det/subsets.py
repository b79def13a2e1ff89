"""Label subsets of a Pi3DET platform's training split (1/5/10/20/50/100 %).

The same rule as the segmentation subsets (:mod:`omnilidar.data.subsets`):
one frame out of every k = round(1 / f) of the ``<platform>_train`` split in
index order, no randomness. Pi3DET frames need boxes, not point labels, so a
frame without a label file is fine; a subset whose frames hold no box of the
platform's classes is an error (nothing to train on).
"""

from __future__ import annotations

from pathlib import Path

from omnilidar.data.index import read_index
from omnilidar.data.subsets import FORMAT, every_k, select_every_k
from omnilidar.errors import InputError
from omnilidar.io import pi3det
from omnilidar.manifest import digest


def make_det_subset(index_path: str | Path, platform: str, fraction: float) -> dict:
    """The subset of ``<platform>_train`` of a Pi3DET index, in the subset-file format."""
    from omnilidar.downstream.det.data_config import PLATFORMS

    index = read_index(index_path)
    if index.get("dataset") != "pi3det":
        raise InputError(index_path, f"detection subsets need a pi3det index, got {index.get('dataset')}")
    split = f"{platform}_train"
    entries = index.get("splits", {}).get(split)
    if not entries:
        raise InputError(index_path, f"has no frames in split {split!r} (splits: {', '.join(index.get('splits', {}))})")
    chosen = select_every_k(entries, fraction)
    classes = pi3det.PLATFORM_CLASSES[PLATFORMS[platform]]
    boxes = 0
    for infos_path in sorted({e["infos"] for e in chosen}):
        infos = pi3det.read_infos(infos_path)
        picked = {int(e["info_index"]) for e in chosen if e["infos"] == infos_path}
        boxes += sum(int(sum(n in classes for n in infos[i].get("annos", {}).get("gt_names", [])))
                     for i in picked)
    if boxes == 0:
        raise InputError(index_path, f"the {100 * fraction:g} % subset of {split} ({len(chosen)} frames) holds no "
                                     f"{'/'.join(classes)} box; a detector cannot be trained on it")
    return {"format": FORMAT, "dataset": "pi3det", "split": split, "fraction": float(fraction),
            "every": every_k(fraction), "num_scans": len(chosen), "source_scans": len(entries),
            "num_boxes": boxes, "index_digest": digest(index_path), "entries": chosen}
