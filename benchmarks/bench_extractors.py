"""Throughput of the feature extractors (scans per second) on real KITTI scans.

    python benchmarks/bench_extractors.py [--height 32] [--width 256] [--scans 4] [--repeats 3] [--official-size]

Each extractor runs on batches of --scans range images projected from the real
KITTI scans in OMNILIDAR_REAL_DATA (randomly initialised networks: speed does not
depend on the weights). Default sizes are the CPU self-trained ones
(evaluation.extractors.arch); --official-size uses the published widths
(RangeNet width 32). Prints the median seconds per scan and scans per second.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.data.range_image import RangeImageSpec, encode, project
from omnilidar.io.semantickitti import read_points
from omnilidar.metrics.extractors.views import range_views
from omnilidar.metrics.extractors.weights import build_model, wrap

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import KITTI_SCANS, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
import bench_record  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--height", type=int, default=32)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--scans", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--official-size", action="store_true")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    spec = RangeImageSpec(args.height, args.width, 3.0, -25.0, 1.45, 80.0)
    imgs = []
    for f in real_files_or_exit(KITTI_SCANS):
        proj = project(read_points(f), spec)
        imgs.append(encode(proj.range_img, proj.intensity_img, spec))
    batch = np.stack([imgs[i % len(imgs)] for i in range(args.scans)])
    width = 32 if args.official_size else 8
    archs = {"frd": {"in_channels": 5, "depth": 53, "width": width},
             "frid": {"in_channels": 4, "depth": 21, "width": width},
             "fsvd": {"width": "W16"}, "fpvd": {"width": "W16"},
             "fpd": {"num_classes": 16 if args.official_size else 19}}
    t0 = time.perf_counter()
    views = range_views(batch, spec)
    print(f"views: {(time.perf_counter() - t0) / args.scans * 1e3:.1f} ms/scan ({args.height}x{args.width}, "
          f"torch threads {torch.get_num_threads()})")
    rates = {}
    for kind, arch in archs.items():
        ext = wrap(kind, build_model(kind, arch, generator=torch.Generator().manual_seed(0)))
        ext(views)  # warm-up
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            ext(views)
            times.append((time.perf_counter() - t0) / args.scans)
        med = statistics.median(times)
        print(f"{kind:5s} {str(arch):48s} median {med:.3f} s/scan  {1 / med:.2f} scans/s")
        rates[kind] = 1 / med
    size = "published widths" if args.official_size else "CPU self-trained sizes"
    bench_record.write(args.out, [{
        "what": f"feature extractors at {args.height}x{args.width} ({size}): "
                + " / ".join(k.upper() for k in rates),
        "median": " / ".join(f"{r:.1f}" for r in rates.values()) + f" scans/s ({torch.get_num_threads()} threads)"}],
        {"scans_per_s": rates, "archs": archs})


if __name__ == "__main__":
    main()
