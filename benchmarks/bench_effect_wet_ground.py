"""Wet ground on real KITTI scans: time per scan (one thread), fidelity per
severity, and the accuracy/time sweep over FIDELITY_LEVELS. Run:

    python benchmarks/bench_effect_wet_ground.py [--repeats 15] [--seeds 3]

Prints, per scan and severity: fractions of all points changed / lost / added,
lost fraction of the ground, mean relative and absolute intensity shift of the
changed points, and the median apply time; then the sweep (time and error of
the lost fraction and of the mean intensity shift against the highest-fidelity
setting, averaged over seeds) on kitti_object/velodyne/000001.bin.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.domains.effects import wet_ground as W  # noqa: E402
from omnilidar.domains.ground import estimate_ground  # noqa: E402
from omnilidar.lidar.scan import Scan  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import bench_record  # noqa: E402
from real_samples import KITTI_SCANS, SEMANTICKITTI_SCAN, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
SENSOR = PRESETS["kitti_hdl64e"]


def load(path: Path) -> Scan:
    return Scan(np.fromfile(path, np.float32).reshape(-1, 4))


def median_s(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--seeds", type=int, default=3)
    bench_record.out_arg(ap)
    args = ap.parse_args()
    scans = real_files_or_exit(KITTI_SCANS, SEMANTICKITTI_SCAN)
    rng = np.random.default_rng(0)

    print("fidelity per scan and severity (fractions of all points; shift of changed ground points)")
    print(f"{'scan':>22} {'severity':>9} {'changed':>8} {'lost':>7} {'added':>6} {'lost/gnd':>8} "
          f"{'rel.shift':>9} {'abs.shift':>9} {'ms':>7} {'gnd ms':>7}")
    apply_ms, ground_ms = [], []
    for path in scans:
        scan = load(path)
        ground = estimate_ground(scan, SENSOR)
        t_ground = median_s(lambda: estimate_ground(scan, SENSOR), max(3, args.repeats // 3))
        name = "/".join(path.parts[-3:])[-22:]
        for sev in W.SEVERITIES:
            params = W.draw_params(sev, rng)
            out, info = W.apply(scan, params, SENSOR, np.random.default_rng(0), ground=ground, return_info=True)
            stats = W.fidelity_summary(scan, out, info)
            kept = ~info["lost"]
            ch = info["changed"][kept]
            old = scan.intensity[kept][ch].astype(np.float64)
            rel = float(np.mean(out.intensity[ch] / old - 1.0)) if ch.any() else 0.0
            t = median_s(lambda: W.apply(scan, params, SENSOR, np.random.default_rng(0), ground=ground), args.repeats)
            apply_ms.append(t * 1e3)
            ground_ms.append(t_ground * 1e3)
            print(f"{name:>22} {sev:>9} {stats['changed']:8.4f} {stats['lost']:7.4f} {stats['added']:6.3f} "
                  f"{info['lost'].sum() / max(ground.sum(), 1):8.4f} {rel:9.4f} {stats['mean_shift']:9.4f} "
                  f"{t * 1e3:7.2f} {t_ground * 1e3:7.2f}")

    scan = load(scans[1])
    seeds = list(range(args.seeds))
    print(f"\naccuracy/time sweep on {scans[1].name} (one knob varied, the other at highest fidelity "
          f"{W.HIGHEST_FIDELITY}; errors vs highest, mean over {len(seeds)} seeds)")
    print(f"{'severity':>9} {'knob':>11} {'value':>6} {'ms':>7} {'x vs top':>8} {'lost':>7} {'err lost':>9} {'err shift':>9}")
    for sev in W.SEVERITIES:
        rows = W.accuracy_time_curve(scan, SENSOR, sev, seeds, repeats=max(3, args.repeats // 3))
        top = [r for r in rows if r["knob"] == "range_bins" and r["value"] == W.HIGHEST_FIDELITY["range_bins"]][0]
        for r in rows:
            print(f"{sev:>9} {r['knob']:>11} {r['value']:>6} {r['time_s'] * 1e3:7.2f} "
                  f"{r['time_s'] / top['time_s']:8.2f} {r['lost']:7.4f} {r['err_lost']:9.5f} {r['err_mean_shift']:9.5f}")
    print(f"\nDEFAULT_FIDELITY = {W.DEFAULT_FIDELITY}")
    bench_record.write(args.out, [{
        "what": f"wet ground (+ ground estimation), {len(scans)} real scans x {len(W.SEVERITIES)} severities",
        "median": f"{min(apply_ms):.0f}-{max(apply_ms):.0f} ms (+ {min(ground_ms):.0f}-{max(ground_ms):.0f} ms)",
        "target": "<= 0.05 s (anchor 0.05-0.08 s)"}], {"apply_ms": apply_ms, "ground_ms": ground_ms, "threads": 1})


if __name__ == "__main__":
    main()
