"""Dataset I/O speed on the real samples (OMNILIDAR_REAL_DATA): validated readers/writers vs bare numpy.

Prints the median time of each operation and its ratio to the bare-numpy
baseline (the cost of validation and atomic writes). Run:

    python benchmarks/io_readers.py [--repeats 30]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from omnilidar.io import kitti_object, nuscenes, semantickitti
from omnilidar.geometry.boxes import points_in_boxes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import NUSCENES_SWEEP, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)


def median_ms(fn, repeats: int) -> float:
    fn()  # warm caches
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def row(name: str, ms: float, base: float | None = None) -> None:
    ratio = f"  x{ms / base:5.2f} vs numpy" if base else ""
    print(f"{name:<48s} {ms:8.3f} ms{ratio}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    r = parser.parse_args().repeats
    kitti, nusc, label, calib = real_files_or_exit(
        "kitti_object/velodyne/000001.bin", NUSCENES_SWEEP, "kitti_object/label_2/000001.txt",
        "kitti_object/calib/000001.txt")

    scan = semantickitti.read_scan(kitti)
    print(f"KITTI scan: {len(scan)} points; nuScenes sweep: {len(nuscenes.read_points(nusc))} points")

    base = median_ms(lambda: np.fromfile(kitti, np.float32).reshape(-1, 4), r)
    row("np.fromfile KITTI .bin", base)
    row("semantickitti.read_scan", median_ms(lambda: semantickitti.read_scan(kitti), r), base)

    base = median_ms(lambda: np.fromfile(nusc, np.float32).reshape(-1, 5), r)
    row("np.fromfile nuScenes .pcd.bin", base)
    row("nuscenes.read_scan", median_ms(lambda: nuscenes.read_scan(nusc), r), base)

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "x.bin"
        base = median_ms(lambda: scan.points.tofile(out), r)
        row("ndarray.tofile KITTI scan", base)
        row("semantickitti.write_scan (validated, atomic)", median_ms(lambda: semantickitti.write_scan(scan, out), r), base)
        labels = np.random.default_rng(0).choice(list(semantickitti.LEARNING_MAP), len(scan)).astype(np.uint16)
        lab = Path(tmp) / "x.label"
        semantickitti.write_label(lab, labels, None)
        base = median_ms(lambda: np.fromfile(lab, np.uint32), r)
        row("np.fromfile .label", base)
        row("semantickitti.read_label", median_ms(lambda: semantickitti.read_label(lab, len(scan)), r), base)
        row("to_train_ids (LUT)", median_ms(lambda: semantickitti.to_train_ids(labels), r))

    boxes = kitti_object.read_boxes_lidar(label, calib)
    row(f"points_in_boxes {len(scan)} pts x {len(boxes)} boxes", median_ms(lambda: points_in_boxes(scan.points, boxes), r))
    rng = np.random.default_rng(0)
    many = np.column_stack([rng.uniform(-40, 40, (50, 2)), rng.uniform(-1, 0, 50),
                            rng.uniform(1, 5, (50, 3)), rng.uniform(-np.pi, np.pi, 50)])
    row(f"points_in_boxes {len(scan)} pts x 50 boxes", median_ms(lambda: points_in_boxes(scan.points, many), r))
    row("read_boxes_lidar (label + calib)", median_ms(lambda: kitti_object.read_boxes_lidar(label, calib), r))


if __name__ == "__main__":
    main()
