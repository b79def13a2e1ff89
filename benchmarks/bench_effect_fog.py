"""Fog effect: time per scan (one thread), fidelity on real KITTI scans, accuracy/time sweep.

Run: python benchmarks/bench_effect_fog.py
"""

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.domains.effects import fog  # noqa: E402
from omnilidar.lidar.scan import Scan  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
import bench_record  # noqa: E402
SENSOR = PRESETS["kitti_hdl64e"]
REPEATS = 15


def load(name: str) -> Scan:
    return Scan(np.fromfile(real_files_or_exit(f"kitti_object/velodyne/{name}.bin")[0], np.float32).reshape(-1, 4))


def timing(scan: Scan) -> dict:
    print(f"== time per scan, {len(scan)} points, 1 thread (median of {REPEATS}) ==")
    cold = []
    for alpha in fog.ALPHAS[1:]:
        t0 = time.perf_counter()
        fog._build_table(alpha, fog.DEFAULT_FIDELITY["r0_step"], fog.DEFAULT_FIDELITY["quad_nodes"])
        cold.append(time.perf_counter() - t0)
    print(f"table build per alpha (cold, once per process): median {1e3 * np.median(cold):.1f} ms")
    medians = {"table_build_ms": 1e3 * float(np.median(cold))}
    for severity in fog.SEVERITIES:
        per_alpha = []
        for alpha in fog.ALPHAS[1:]:
            params = {"alpha": alpha, "beta": fog.SEVERITIES[severity]["beta"], "range_jitter": 1.0}
            fog.apply(scan, params, SENSOR, np.random.default_rng(0))  # warm the table cache
            times = []
            for k in range(REPEATS):
                t0 = time.perf_counter()
                fog.apply(scan, params, SENSOR, np.random.default_rng(k))
                times.append(time.perf_counter() - t0)
            per_alpha.append(np.median(times))
        drawn = []
        for k in range(REPEATS):
            rng = np.random.default_rng(k)
            params = fog.draw_params(severity, rng)
            t0 = time.perf_counter()
            fog.apply(scan, params, SENSOR, rng)
            drawn.append(time.perf_counter() - t0)
        print(f"{severity:9s} drawn alpha: median {1e3 * np.median(drawn):6.1f} ms | "
              f"alpha>0 each: {' '.join(f'{1e3 * t:5.1f}' for t in per_alpha)} ms | "
              f"ratio to 0.1 s target {np.max(per_alpha) / 0.1:.2f}")
        medians[severity] = {"drawn_ms": 1e3 * float(np.median(drawn)), "per_alpha_ms": [1e3 * float(t) for t in per_alpha]}
    return medians


def fidelity(name: str) -> None:
    scan = load(name)
    pts = scan.points
    print(f"\n== fidelity on kitti_object/{name}.bin ({len(scan)} points) ==")
    print("severity  alpha  changed   lost    fog  fog range m (min/med/max)  fog I mean/max  dI kept")
    for severity, spec in fog.SEVERITIES.items():
        for alpha in fog.ALPHAS[1:]:
            out, info = fog.apply(scan, {"alpha": alpha, "beta": spec["beta"], "range_jitter": 1.0},
                                  SENSOR, np.random.default_rng(0), return_info=True)
            w = info["weather"]
            kept = ~info["lost"]
            r = np.linalg.norm(out.points[w, :3], axis=1)
            hard = ~w
            d_int = float(np.mean(out.points[hard, 3] - pts[kept][hard, 3])) if hard.any() else 0.0
            fog_txt = (f"{r.min():5.2f}/{np.median(r):5.2f}/{r.max():5.2f}" if w.any() else "    -")
            fog_i = f"{out.points[w, 3].mean():.4f}/{out.points[w, 3].max():.4f}" if w.any() else "-"
            print(f"{severity:9s} {alpha:5.3f} {info['changed'].mean():7.3f} {info['lost'].mean():6.3f} "
                  f"{w.sum() / len(scan):6.3f}  {fog_txt:26s} {fog_i:15s} {d_int:+.4f}")


def sweep(scan: Scan) -> None:
    print("\n== accuracy/time over FIDELITY_LEVELS (moderate, 5 alphas x 3 seeds, vs highest fidelity) ==")
    rows = fog.accuracy_time_curve(scan, SENSOR, "moderate", seeds=[0, 1, 2])
    print("knob        value  table_s   apply_ms  err_fog_frac  err_lost_frac  err_mean_I  err_fog_range_m")
    for row in rows:
        mark = " *" if row["is_default"] else ""
        print(f"{row['knob']:10s} {row['value']:6g} {row['table_s']:8.4f} {1e3 * row['apply_s']:9.2f} "
              f"{row['err_fog_fraction']:13.2e} {row['err_lost_fraction']:13.2e} "
              f"{row['err_mean_intensity']:11.2e} {row['err_fog_range_m']:11.2e}{mark}")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    bench_record.out_arg(parser)
    args = parser.parse_args()
    main_scan = load("000001")
    medians = timing(main_scan)
    drawn = [medians[s]["drawn_ms"] for s in fog.SEVERITIES]
    bench_record.write(args.out, [{
        "what": f"fog, per {len(main_scan) / 1e3:.0f}k-point scan",
        "median": " / ".join(f"{ms:.0f}" for ms in drawn) + f" ms ({' / '.join(fog.SEVERITIES)})",
        "target": "<= 0.1 s (anchor ~0.6 s)"}], {"points": len(main_scan), "threads": 1, "timing": medians})
    for scan_name in ("000000", "000001"):
        fidelity(scan_name)
    sweep(main_scan)
