"""Projection / back-projection throughput on a real 120k-point KITTI scan, one thread.

    python benchmarks/bench_projection.py [--repeats 30]
"""

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.data.range_image import RangeImageSpec, decode, encode, project, unproject  # noqa: E402
from omnilidar.data.rings import recover_rings  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
import bench_record  # noqa: E402


def median_ms(fn, repeats):
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=30)
    bench_record.out_arg(ap)
    args = ap.parse_args()
    (scan,) = real_files_or_exit("kitti_object/velodyne/000001.bin")
    pts = np.fromfile(scan, np.float32).reshape(-1, 4)
    spec = RangeImageSpec.from_sensor(PRESETS["kitti_hdl64e"])
    proj = project(pts, spec)
    img = encode(proj.range_img, proj.intensity_img, spec)
    d, i, m = decode(img, spec)
    n_pix = int(m.sum())
    rows = [
        ("project", median_ms(lambda: project(pts, spec), args.repeats), len(pts)),
        ("encode", median_ms(lambda: encode(proj.range_img, proj.intensity_img, spec), args.repeats), n_pix),
        ("decode", median_ms(lambda: decode(img, spec), args.repeats), n_pix),
        ("unproject", median_ms(lambda: unproject(d, i, spec, mask=m), args.repeats), n_pix),
        ("recover_rings", median_ms(lambda: recover_rings(pts, PRESETS["kitti_hdl64e"]), max(5, args.repeats // 4)), len(pts)),
    ]
    print(f"scan {scan.name}: {len(pts)} points, image {spec.height}x{spec.width}, {n_pix} returns; 1 thread")
    print(f"{'stage':<15}{'median ms':>11}{'points/s':>14}")
    for name, ms, count in rows:
        print(f"{name:<15}{ms:>11.2f}{count / (ms * 1e-3):>14.3e}")
    target = 20.0
    print(f"projection target <= {target:.0f} ms: ratio {rows[0][1] / target:.2f} ({'met' if rows[0][1] <= target else 'MISSED'})")
    ms = {name: ms for name, ms, _ in rows}
    bench_record.write(args.out, [
        {"what": f"project a {len(pts) / 1e3:.0f}k-point KITTI scan to {spec.height}x{spec.width}",
         "median": f"{ms['project']:.1f} ms ({len(pts) / ms['project'] / 1e3:.1f} M points/s)", "target": f"<= {target:.0f} ms"},
        {"what": "encode / decode / unproject", "median": f"{ms['encode']:.1f} / {ms['decode']:.1f} / {ms['unproject']:.1f} ms"},
        {"what": "ring recovery with calibration", "median": f"{ms['recover_rings']:.0f} ms"},
    ], {"median_ms": ms, "points": len(pts), "returns": n_pix, "threads": 1})


if __name__ == "__main__":
    main()
