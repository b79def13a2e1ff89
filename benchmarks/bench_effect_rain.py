"""Rain effect: time per scan per severity, fidelity on real KITTI, accuracy/time sweep.

    python benchmarks/bench_effect_rain.py [--quick]

Runs on ONE thread.  Prints medians of wall and CPU seconds per 120k-point
scan (kitti_object/velodyne/000001.bin) per severity at the band's nominal
(geometric-centre) rate, the fidelity statistics on both real KITTI scans,
alpha against LISA's measured values, and the accuracy/time curve of every
fidelity knob (others at the highest setting) against the highest setting.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from omnilidar.domains.effects import rain  # noqa: E402
from omnilidar.domains.effects._mie import mie_efficiencies  # noqa: E402
from omnilidar.lidar.scan import Scan  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import bench_record  # noqa: E402
from real_samples import KITTI_SCANS, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
SENSOR = PRESETS["kitti_hdl64e"]
LISA_ALPHA = {5.0: 0.001, 100.0: 0.0067, 2500.0: 0.05}  # extinction (1/m) LISA quotes as measured, per mm/h


def load(name: str) -> Scan:
    return Scan(np.fromfile(real_files_or_exit(f"kitti_object/velodyne/{name}.bin")[0], np.float32).reshape(-1, 4))


def timed(scan: Scan, params: dict, seeds, fidelity=None):
    wall, cpu, stats = [], [], []
    for seed in seeds:
        t0, c0 = time.perf_counter(), time.process_time()
        out, info = rain.apply(scan, params, SENSOR, np.random.default_rng(seed), fidelity=fidelity, return_info=True)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        stats.append(rain.fidelity_summary(scan, out, info, SENSOR))
    mean = {k: float(np.nanmean([s[k] for s in stats])) for k in stats[0]}
    return float(np.median(wall)), float(np.median(cpu)), mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer seeds, moderate-only sweep")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    real_files_or_exit(KITTI_SCANS)  # one line before any table
    seeds = range(3 if args.quick else 7)

    print("== extinction alpha (1/m) vs LISA's measured values")
    alphas = {}
    for rate, measured in LISA_ALPHA.items():
        alphas[rate] = a = rain.extinction_coefficient(rate)
        print(f"  {rate:7.0f} mm/h  alpha={a:.5f}  measured={measured:.4f}  ratio={a / measured:.3f}")
    x = np.linspace(np.pi * 0.5e-3 / rain.WAVELENGTH_M, np.pi * 1.0e-3 / rain.WAVELENGTH_M, 64)
    q_back = mie_efficiencies(x, rain.M_WATER)[2]
    print(f"  Mie Q_back of 0.5-1 mm spheres: mean {q_back.mean():.2f} (Fresnel rho_w used per drop: {rain.RHO_WATER:.4f})")

    scan = load("000001")
    rain.apply(scan, {"rate_mm_h": 1.0}, SENSOR, np.random.default_rng(0))  # warm the Mie cache
    print(f"\n== time per scan, {len(scan)} points, one thread, median of {len(seeds)} seeds (DEFAULT_FIDELITY)")
    base, walls = None, {}
    for sev in rain.SEVERITIES:
        params = rain.nominal_params(sev)
        wall, cpu, _ = timed(scan, params, seeds)
        base = base or cpu
        walls[sev] = wall
        print(f"  {sev:9s} {params['rate_mm_h']:7.1f} mm/h  wall {wall:.3f} s  cpu {cpu:.3f} s  (cpu / light {cpu / base:.2f})")

    print("\n== fidelity on real KITTI (mean over seeds; nominal rate per severity, and band edges)")
    hdr = "  scan    sev/rate          lost    rain   changed  added  dI(mean)  rain r med/p95   rain I"
    print(hdr)
    for name in ("000000", "000001"):
        s = load(name)
        for sev, spec in rain.SEVERITIES.items():
            lo, hi = spec["rate_mm_h"]
            for label, rate in (("  low", lo), (sev, rain.nominal_params(sev)["rate_mm_h"]), ("  high", hi)):
                _, _, m = timed(s, {"rate_mm_h": rate}, seeds[:3] if label != sev else seeds)
                print(
                    f"  {name}  {label:9s}{rate:7.1f}  {m['frac_lost']:.4f}  {m['frac_rain']:.4f}  {m['frac_changed']:.4f}"
                    f"  {m['frac_added']:.2f}  {m['mean_intensity_shift']:+.4f}  {m['rain_range_median']:5.2f}/{m['rain_range_p95']:5.2f}"
                    f"   {m['rain_intensity_mean']:.5f}"
                )

    sweep = ("moderate",) if args.quick else ("moderate", "heavy")
    for sev in sweep:
        print(f"\n== accuracy/time sweep, {sev} ({rain.nominal_params(sev)['rate_mm_h']:.0f} mm/h), seeds {list(seeds)[:5]}")
        print("  knob                value  wall s  cpu s   alpha     err_lost  err_rain  err_dI    (mc se rain)")
        for row in rain.accuracy_time_curve(scan, SENSOR, sev, seeds=list(seeds)[:5]):
            print(
                f"  {row['knob']:18s} {row['value']!s:>7}  {row['seconds']:.3f}  {row['cpu_seconds']:.3f}  {row['alpha']:.6f}"
                f"  {row['err_frac_lost']:.5f}  {row['err_frac_rain']:.5f}  {row['err_mean_intensity_shift']:.5f}"
                f"  ({row['mc_se_frac_rain']:.5f})"
            )
    print(f"\nDEFAULT_FIDELITY = {rain.DEFAULT_FIDELITY}")
    bench_record.write(args.out, [{
        "what": f"rain, per {len(scan) / 1e3:.0f}k-point scan",
        "median": " / ".join(f"{w:.2f}" for w in walls.values()) + f" s ({' / '.join(walls)})",
        "target": "<= 0.5 s (anchor 7-9 s)"}, {
        "what": f"rain extinction at {' / '.join(f'{r:g}' for r in alphas)} mm/h (our Mie series)",
        "median": " / ".join(f"{a:.3g}" for a in alphas.values()) + " per m",
        "target": "LISA's measured " + " / ".join(f"{m:g}" for m in LISA_ALPHA.values())}],
        {"wall_s": walls, "seeds": len(seeds), "threads": 1,
         "extinction_per_m": {f"{r:g}": a for r, a in alphas.items()}})


if __name__ == "__main__":
    main()
