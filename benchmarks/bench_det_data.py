"""CPU time of the detection data path per frame (one core): a real-size 120k-point scan at
Pi3DET's voxel size [0.1, 0.1, 0.15] and at the CPU default's [0.2, 0.2, 0.15].

Shift, augmentation, range filter, shuffle and voxelization (``DetScanDataset`` minus the file
read) against a point-by-point voxelizer in Python (spconv's loop, the brute-force baseline);
median over repeats.

    python benchmarks/bench_det_data.py [--repeats 5] [--points 120000]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.config import validate  # noqa: E402
from omnilidar.downstream.det.augment import augment, limit_heading  # noqa: E402
from omnilidar.downstream.det.voxelize import points_to_voxels  # noqa: E402


def python_voxelizer(points, voxel_size, pcr, max_points, max_voxels):
    lo, vs = np.asarray(pcr[:3]), np.asarray(voxel_size)
    grid = np.round((np.asarray(pcr[3:]) - lo) / vs).astype(int)
    slots, counts = {}, []
    for p in points:
        c = tuple(int(v) for v in np.floor((p[:3] - lo) / vs))
        if min(c) < 0 or any(c[k] >= grid[k] for k in range(3)):
            continue
        if c not in slots:
            if len(slots) >= max_voxels:
                continue
            slots[c] = len(slots)
            counts.append(0)
        if counts[slots[c]] < max_points:
            counts[slots[c]] += 1
    return len(slots)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--points", type=int, default=120_000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.points
    r = rng.uniform(2, 75, n)
    a = rng.uniform(-np.pi, np.pi, n)
    points = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-2.5, 3, n), rng.uniform(0, 1, n)], 1).astype(np.float32)
    boxes = np.tile(np.array([[20, 5, -1, 4, 2, 1.5, 0.3]], np.float32), (30, 1))
    det = validate({"det": {}}, "downstream.schema.yaml")["det"]
    pcr = det["point_cloud_range"]
    for voxel in ([0.1, 0.1, 0.15], [0.2, 0.2, 0.15]):
        times, count = [], 0
        for k in range(args.repeats):
            t = time.perf_counter()
            p, b = augment(points, boxes, det["augmentation"], np.random.default_rng(k))
            b[:, 6] = limit_heading(b[:, 6])
            keep = np.all((p[:, :3] >= pcr[:3]) & (p[:, :3] <= pcr[3:]), axis=1)
            p = p[keep][np.random.default_rng(k).permutation(int(keep.sum()))]
            v, c, num = points_to_voxels(p, voxel, pcr, 5, 90_000)
            times.append(time.perf_counter() - t)
            count = len(v)
        t = time.perf_counter()
        ref = python_voxelizer(p, voxel, pcr, 5, 90_000)
        baseline = time.perf_counter() - t
        assert ref == count
        print(f"voxel {voxel}: {len(p)} points in range -> {count} voxels; data path {1000 * np.median(times):.1f} ms "
              f"per frame (median of {args.repeats}); point-by-point voxelizer {1000 * baseline:.0f} ms "
              f"({baseline / np.median(times):.0f}x)")


if __name__ == "__main__":
    main()
