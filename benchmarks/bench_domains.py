"""Time per scan of each default domain's scene on real KITTI scans (one core).

For every domain of the default config that reads vehicle data: the builder
(severity and parameter draws, ground estimation when needed, the effects) and
the range-image encoding, median over scans x repeats; plus each corruption at
heavy severity. Prints medians and the ratio to the anchors' reported times
(REFERENCE.md section 4).

    python benchmarks/bench_domains.py [--repeats 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, as the targets are stated
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.config import section_defaults  # noqa: E402
from omnilidar.data.range_image import RangeImageSpec, to_range_image  # noqa: E402
from omnilidar.domains.builder import build_scan, scan_rng  # noqa: E402
from omnilidar.domains.corruption import CORRUPTIONS, corruption_scene  # noqa: E402
from omnilidar.domains.spec import domains_from_settings  # noqa: E402
from omnilidar.io import semantickitti  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import KITTI_SCANS, SEMANTICKITTI_SCAN, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
# Anchors' seconds per scan (REFERENCE.md section 4), for the ratio column.
ANCHOR_S = {"fog": 0.6, "wet_ground": 0.065, "snow": 38.0, "rain": 8.0}


def time_scene(name, scene, scans, sensor, spec, repeats):
    times, ran = [], 0
    for k, scan in enumerate(scans):
        for r in range(repeats):
            t0 = time.perf_counter()
            out, _ = build_scan(scan, scene, sensor, scan_rng(0, k, r))
            to_range_image(out, spec)
            times.append(time.perf_counter() - t0)
            ran += 1
    return float(np.median(times)), ran


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    scans = [semantickitti.read_scan(p) for p in real_files_or_exit(KITTI_SCANS, SEMANTICKITTI_SCAN)]
    sensor = PRESETS["kitti_hdl64e"]
    spec = RangeImageSpec.from_sensor(sensor)
    print(f"{len(scans)} real scans ({', '.join(str(len(s)) for s in scans)} points), {args.repeats} repeats, "
          f"OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}")
    print(f"{'scene':28s} {'median s/scan':>14s} {'anchor s':>9s} {'speed-up':>9s}")
    domains = domains_from_settings(section_defaults("domains"))
    rows = [(f"domain {d.name}", d.scene, d.scene.effects[0].name if d.scene.effects else None)
            for d in domains.values() if d.dataset == "semantickitti"]
    rows += [(f"corrupted {c}/heavy", corruption_scene(c, "heavy"), CORRUPTIONS[c]) for c in CORRUPTIONS]
    for label, scene, effect in rows:
        median, _ = time_scene(label, scene, scans, sensor, spec, args.repeats)
        anchor = ANCHOR_S.get(effect)
        ratio = f"{anchor / median:9.1f}" if anchor else f"{'-':>9s}"
        print(f"{label:28s} {median:14.3f} {anchor if anchor else '-':>9} {ratio}")


if __name__ == "__main__":
    main()
