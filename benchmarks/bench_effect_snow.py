"""Snow effect: median time per scan per severity on the real 120k-point KITTI scan
(one thread), fidelity statistics, and the accuracy/time sweep over FIDELITY_LEVELS.

    python benchmarks/bench_effect_snow.py [--repeats 5] [--seeds 3] [--no-sweep]
"""

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.domains.effects import snow  # noqa: E402
from omnilidar.lidar.scan import Scan  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import KITTI_SCANS, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
import bench_record  # noqa: E402
ANCHOR_S = 35.0  # anchor: ~35-42 s CPU per scan (REFERENCE 4)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--no-sweep", action="store_true")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    sensor = PRESETS["kitti_hdl64e"]
    scans = {p.stem: Scan(np.fromfile(p, np.float32).reshape(-1, 4)) for p in real_files_or_exit(KITTI_SCANS)}
    scan = scans["000001"]
    print(f"snow on kitti_object/velodyne/000001.bin ({len(scan)} points), one thread, fidelity {snow.DEFAULT_FIDELITY}")
    print(f"{'severity':9s} {'median_s':>9s} {'anchor/ours':>11s}")
    medians = {}
    for sev, params in snow.SEVERITIES.items():
        times = []
        for i in range(args.repeats):
            t0 = time.perf_counter()
            snow.apply(scan, params, sensor, np.random.default_rng(i))
            times.append(time.perf_counter() - t0)
        med = float(np.median(times))
        print(f"{sev:9s} {med:9.3f} {ANCHOR_S / med:11.0f}x")
        medians[sev] = med
    bench_record.write(args.out, [{
        "what": f"snow, per {len(scan) / 1e3:.0f}k-point scan",
        "median": " / ".join(f"{m:.2f}" for m in medians.values()) + f" s ({' / '.join(medians)})",
        "target": "<= 1 s (anchor 33-42 s)"}], {"median_s": medians, "repeats": args.repeats, "threads": 1})

    print("\nfidelity per scan and severity (mean over seeds; fractions of input points)")
    keys = ("changed", "lost", "weather", "dimmed", "intensity_shift_mean", "weather_range_median",
            "weather_range_p90", "weather_intensity_mean")
    print(f"{'scan':7s} {'severity':9s} " + " ".join(f"{k[:16]:>16s}" for k in keys))
    for name, sc in scans.items():
        for sev, params in snow.SEVERITIES.items():
            rows = [snow.summary(sc, *snow.apply(sc, params, sensor, np.random.default_rng(s), return_info=True))
                    for s in range(args.seeds)]
            print(f"{name:7s} {sev:9s} " + " ".join(f"{np.nanmean([r[k] for r in rows]):16.5f}" for k in keys))

    if args.no_sweep:
        return
    print("\naccuracy/time sweep (one knob varied, others at highest fidelity; error vs highest fidelity)")
    print(f"{'severity':9s} {'knob':12s} {'value':>8s} {'time_s':>8s} {'lost':>8s} {'weather':>8s} {'changed':>8s}"
          f" {'dI':>10s} {'err_lost':>9s} {'err_weath':>9s} {'err_dI':>9s}")
    for sev in snow.SEVERITIES:
        for row in snow.accuracy_time_curve(scan, sensor, sev, seeds=range(args.seeds)):
            print(f"{sev:9s} {row['knob']:12s} {row['value']:8g} {row['time_s']:8.3f} {row['lost']:8.5f}"
                  f" {row['weather']:8.5f} {row['changed']:8.4f} {row['intensity_shift_mean']:10.2e}"
                  f" {row['err_lost']:9.2e} {row['err_weather']:9.2e} {row['err_intensity_shift_mean']:9.2e}")


if __name__ == "__main__":
    main()
