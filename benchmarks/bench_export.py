"""Wall time of ``omnilidar export`` per scan, each format, on real-size generated shards (one core).

Writes shards of 120k-point scans with 10 boxes each (sample shard, pseudo-label shard,
pseudo-box shard, all with their manifests) into a temporary directory, then times the
in-process export command; the median over repeats, in ms per scan.

    python benchmarks/bench_export.py [--scans 20] [--points 120000] [--repeats 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from omnilidar.cli import main  # noqa: E402
from omnilidar.downstream.det.pseudo_boxes import write_shard  # noqa: E402
from omnilidar.io import semantickitti  # noqa: E402
from omnilidar.io.atomic import atomic_path  # noqa: E402


def make_shards(root: Path, scans: int, points: int, seed: int = 0) -> tuple[Path, Path, Path]:
    rng = np.random.default_rng(seed)
    samples, labels, boxes = root / "samples", root / "labels", root / "boxes"
    preds = {}
    with atomic_path(samples) as tmp:
        (tmp / "velodyne").mkdir(parents=True)
        for i in range(scans):
            pts = np.column_stack([rng.uniform(-70, 70, (points, 2)), rng.uniform(-2, 3, points), rng.uniform(0, 1, points)])
            pts.astype(np.float32).tofile(tmp / "velodyne" / f"{i:06d}.bin")
            centres = np.column_stack([rng.uniform(5, 60, (10, 2)), np.full(10, -0.9)])
            preds[f"{i:06d}"] = {"boxes": np.column_stack([centres, np.tile([3.9, 1.6, 1.56], (10, 1)),
                                                           rng.uniform(-3, 3, 10)]).astype(np.float32),
                                 "scores": np.ones(10), "names": ["Car"] * 10}
    with atomic_path(labels) as tmp:
        (tmp / "labels").mkdir(parents=True)
        for i in range(scans):
            train = rng.integers(0, semantickitti.NUM_CLASSES, points).astype(np.uint8)
            semantickitti.write_label(tmp / "labels" / f"{i:06d}.label", semantickitti.to_raw_ids(train))
    write_shard(samples, "Quadruped", preds, 0.5, boxes, {"detector": "bench"}, 0.0)
    return samples, labels, boxes


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--points", type=int, default=120_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        samples, labels, boxes = make_shards(root, args.scans, args.points)
        runs = {"openpcdet": ["--boxes", str(boxes)], "mmdet3d-seg": ["--labels", str(labels)],
                "mmdet3d-det": ["--boxes", str(boxes)]}
        print(f"{args.scans} scans x {args.points} points, 10 boxes each; median of {args.repeats}")
        for fmt, extra in runs.items():
            times = []
            for r in range(args.repeats):
                started = time.perf_counter()
                code = main(["export", "--format", fmt, "--samples", str(samples), *extra, "--val-every", "5",
                             "--out", str(root / f"out_{fmt}_{r}")])
                times.append(time.perf_counter() - started)
                assert code == 0
            print(f"{fmt:12s} {1000 * np.median(times) / args.scans:7.1f} ms per scan")


if __name__ == "__main__":
    main_bench()
