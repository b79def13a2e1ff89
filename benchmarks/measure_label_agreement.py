"""How right a labeler's labels of SDEdited scans are: its labels against the labels carried from
each edit's source scan.

    python benchmarks/measure_label_agreement.py \
        --set "fixed labeler, 0.02=data/samples/attempt-prior_edit02/Vehicle=data/pseudo_labels/attempt-prior_edit02/Vehicle=data/carried_labels/attempt-prior_true02/Vehicle"

Each --set is NAME=SCANS=LABELS=TRUTH: a folder of SDEdited sample shards (velodyne/*.bin at any
depth), a labeler's labels of them and the labels carried from their sources (`carry-labels`),
both at the same relative paths with labels/ for velodyne/. The labels and the truth must label
the same scans: an attempt's labels and a `labels: carried` attempt's at the same generator,
strength and seed sample the same scans, which is checked byte for byte against the shard the
carried labels name in their sidecar. Points the source left unlabelled are ignored. Prints mIoU (semantic-kitti-api convention), accuracy and
the IoU of the classes that cost most, per set: the labels link of the SDEdit attempts, measured on
the scans themselves rather than through a student.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import bench_record
from omnilidar.errors import InputError
from omnilidar.io.semantickitti import CLASS_NAMES, read_label, read_points, to_train_ids
from omnilidar.metrics.segmentation import ConfusionMatrix

CLASSES = ("car", "road", "sidewalk", "building", "vegetation", "terrain")  # the classes the scans hold most of


def label_paths(root: Path, scans: Path, scan: Path) -> Path:
    """The label file of ``scan`` (under ``scans``) in the label folder ``root``."""
    return root / scan.relative_to(scans).parent.parent / "labels" / scan.with_suffix(".label").name


def same_scan(scan: Path, truth_shard: Path) -> None:
    """Refuse truth carried onto another scan than ``scan`` (the shard its sidecar names)."""
    sidecar = truth_shard / "sidecar.json"
    if not sidecar.is_file():
        raise InputError(sidecar, "carried labels without a sidecar (made by carry-labels?)")
    carried_onto = Path(json.loads(sidecar.read_text())["samples"]) / "velodyne" / scan.name
    if not carried_onto.is_file() or carried_onto.read_bytes() != scan.read_bytes():
        raise InputError(scan, f"the truth was carried onto another scan ({carried_onto})")


def agreement(scans: Path, labels: Path, truth: Path) -> tuple[dict, int]:
    """Scores of ``labels`` against ``truth`` over every scan under ``scans``, and the scan count."""
    files = sorted(scans.glob("**/velodyne/*.bin"))
    if not files:
        raise InputError(scans, "no velodyne/*.bin scans")
    confusion = ConfusionMatrix(len(CLASS_NAMES) + 1)
    for scan in files:
        count = len(read_points(scan))
        same_scan(scan, label_paths(truth, scans, scan).parent.parent)
        pair = []
        for root in (truth, labels):
            path = label_paths(root, scans, scan)
            if not path.is_file():
                raise InputError(path, "no labels for this scan")
            pair.append(to_train_ids(read_label(path, count)[0]))
        confusion.update(*pair, scan)
    return confusion.result().as_dict(list(CLASS_NAMES)), len(files)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", required=True, metavar="NAME=SCANS=LABELS=TRUTH")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    rows = []
    for item in args.set:
        parts = item.split("=")
        if len(parts) != 4:
            raise SystemExit(f"--set takes NAME=SCANS=LABELS=TRUTH, got {item!r}")
        try:
            scores, count = agreement(*(Path(p) for p in parts[1:]))
        except InputError as err:  # one clear line naming the file, no traceback
            raise SystemExit(f"error: {err}") from None
        rows.append({"set": parts[0], "scans": count, "mIoU": f"{100 * scores['miou']:.2f}",
                     "accuracy": f"{100 * scores['accuracy']:.1f} %",
                     **{f"{c} IoU": f"{100 * scores['iou'][c]:.1f}" for c in CLASSES}})
    columns = ["set", "scans", "mIoU", "accuracy", *[f"{c} IoU" for c in CLASSES]]
    bench_record.print_table(rows, columns)
    bench_record.write(args.out, rows, {}, columns=columns)


if __name__ == "__main__":
    main()
