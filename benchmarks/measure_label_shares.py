"""What the labeler makes of a set of scans: each class's share of the points and their mean remission.

    python benchmarks/measure_label_shares.py \
        --set generated=data/samples/Vehicle=data/pseudo_labels/Vehicle \
        --set "training scans=data/samples/attempt-sources/Vehicle=data/pseudo_labels/attempt-sources/Vehicle"

Each --set is NAME=SCANS=LABELS: a folder holding velodyne/*.bin scans at any depth (sample
shards, a round-tripped pool) and the folder holding their labels at the same relative paths with
labels/ for velodyne/ (pseudo-label shards, as pseudo_label writes them). A student trained on the set learns these class priors: when a generator's scans are
labelled mostly as one class that the real scans hold little of, the student is taught that bias.
Prints one row per class (SemanticKITTI training classes; classes under 0.1 % in every set left
out), each set's share of points in % and, in brackets, the class's mean remission.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import bench_record
from omnilidar.errors import InputError
from omnilidar.io.semantickitti import CLASS_NAMES, read_label, read_points, to_train_ids


def label_shares(samples: Path, labels: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """Per training class (index 0 = ignore): point counts, remission sums, and the number of scans."""
    counts = np.zeros(len(CLASS_NAMES) + 1, dtype=np.int64)
    remission = np.zeros(len(CLASS_NAMES) + 1, dtype=np.float64)
    scans = sorted(samples.glob("**/velodyne/*.bin"))
    if not scans:
        raise InputError(samples, "no velodyne/*.bin scans")
    for scan in scans:
        label = labels / scan.relative_to(samples).parent.parent / "labels" / scan.with_suffix(".label").name
        if not label.is_file():
            raise InputError(label, "no pseudo-labels for this scan")
        points = read_points(scan)
        train = to_train_ids(read_label(label, len(points))[0])
        counts += np.bincount(train, minlength=len(counts))
        remission += np.bincount(train, weights=points[:, 3], minlength=len(counts))
    return counts, remission, len(scans)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", required=True, metavar="NAME=SCANS=LABELS")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    sets = {}
    for item in args.set:
        parts = item.split("=")
        if len(parts) != 3:
            raise SystemExit(f"--set takes NAME=SCANS=LABELS, got {item!r}")
        try:
            sets[parts[0]] = label_shares(Path(parts[1]), Path(parts[2]))
        except InputError as err:  # one clear line naming the file, no traceback
            raise SystemExit(f"error: {err}") from None
    shares = {name: 100 * c / max(c.sum(), 1) for name, (c, _, _) in sets.items()}
    rows = []
    for k, cls in enumerate(CLASS_NAMES, start=1):
        if max(s[k] for s in shares.values()) < 0.1:
            continue
        row = {"class": cls}
        for name, (counts, remission, _) in sets.items():
            mean = remission[k] / counts[k] if counts[k] else float("nan")
            row[name] = f"{shares[name][k]:.1f} ({mean:.2f})"
        rows.append(row)
    columns = ["class", *[f"{name}" for name in sets]]
    for name, (_, _, n) in sets.items():
        print(f"{name}: {n} scans")
    bench_record.print_table(rows, columns)
    bench_record.write(args.out, rows, {}, columns=columns)


if __name__ == "__main__":
    main()
