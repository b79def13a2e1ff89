"""Throughput of the feature-free metrics and time of the Frechet distance.

    python benchmarks/bench_metrics.py [--scans 200] [--repeats 3] [--threads N] [--scipy-4096]

Feature-free metrics on synthetic 120k-point scans (64 beams x 1875 azimuths,
a ground plane plus random obstacles; a pool of distinct scans cycled):
BEV histograms, R2Flow JSD / MMD, LiDM occupancy sums, LiDM JSD and MMD, in
scans per second (median of --repeats). Frechet distance from covariances at
512, 1808 and 4096 dimensions: ours against the anchors' scipy.linalg.sqrtm
formula (512 and 1808; 4096 only with --scipy-4096, it takes minutes), with
medians and ratios, plus ours from features with fewer samples than
dimensions (the Gram route).
"""

import argparse
import os
import sys


def _set_threads(argv):
    # BLAS reads these once, at import: set them before numpy loads
    for i, a in enumerate(argv):
        if a == "--threads" and i + 1 < len(argv):
            for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
                os.environ[var] = argv[i + 1]


_set_threads(sys.argv)

import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402

from omnilidar.metrics.bev import (  # noqa: E402
    bev_histograms,
    bev_jsd,
    bev_mmd,
    lidm_bev_occupancies,
    lidm_jsd,
    lidm_mmd,
    lidm_occupancy_sum,
)
from omnilidar.metrics.frechet import feature_statistics, frechet_distance, frechet_from_features  # noqa: E402

import bench_record  # benchmarks/, the script's folder


def synthetic_scan(rng: np.random.Generator, beams: int = 64, columns: int = 1875) -> np.ndarray:
    """(beams * columns, 4) float32: rays from 1.73 m height hitting the ground
    or a random obstacle (box-like walls at random azimuth sectors)."""
    elev = np.deg2rad(np.linspace(2.0, -24.8, beams))[:, None]
    azim = np.linspace(-np.pi, np.pi, columns, endpoint=False)[None, :]
    ground = np.where(np.sin(elev) < -1e-3, 1.73 / np.maximum(-np.sin(elev), 1e-3), 120.0)
    walls = np.full((1, columns), 200.0)
    for _ in range(rng.integers(8, 20)):
        start = rng.integers(0, columns)
        width = rng.integers(10, 200)
        cols = np.arange(start, start + width) % columns
        walls[0, cols] = np.minimum(walls[0, cols], rng.uniform(4.0, 60.0))
    rng_ = np.minimum(ground, walls / np.cos(elev)) + rng.normal(0.0, 0.02, (beams, columns))
    x = rng_ * np.cos(elev) * np.cos(azim)
    y = rng_ * np.cos(elev) * np.sin(azim)
    z = rng_ * np.sin(elev)
    pts = np.stack([x, y, z, rng.random((beams, columns))], axis=-1).reshape(-1, 4)
    return pts[rng_.reshape(-1) < 100.0].astype(np.float32)


def median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def scipy_frechet(mu1, s1, mu2, s2) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        root = scipy.linalg.sqrtm(s1 @ s2)
    return float(np.real(np.sum((mu1 - mu2) ** 2) + np.trace(s1 + s2 - 2.0 * root)))


def bench_bev(n_scans: int, repeats: int, pool: int, rng: np.random.Generator) -> dict:
    scans_pool = [synthetic_scan(rng) for _ in range(pool)]
    scans = [scans_pool[i % pool] for i in range(n_scans)]
    half = n_scans // 2
    mean_pts = np.mean([len(s) for s in scans_pool])
    print(f"feature-free metrics: {n_scans} synthetic scans ({mean_pts:,.0f} points each), sets of {half} vs {half}")
    hists = bev_histograms(scans)
    occ = lidm_bev_occupancies(scans)
    sums = (lidm_occupancy_sum(scans[:half]), lidm_occupancy_sum(scans[half:]))
    rows = [
        ("BEV histograms (100x100)", n_scans, lambda: bev_histograms(scans)),
        ("R2Flow JSD (from hists)", n_scans, lambda: bev_jsd(hists[:half], hists[half:])),
        ("R2Flow MMD (from hists)", n_scans, lambda: bev_mmd(hists[:half], hists[half:])),
        ("LiDM 5 cm occupancy sums", n_scans, lambda: lidm_occupancy_sum(scans)),
        ("LiDM JSD (from sums)", n_scans, lambda: lidm_jsd(*sums)),
        ("LiDM 0.5 m occupancies", n_scans, lambda: lidm_bev_occupancies(scans)),
        ("LiDM MMD (from occupancies)", n_scans, lambda: lidm_mmd(occ[:half], occ[half:])),
    ]
    print(f"  {'stage':<30}{'median s':>10}{'scans/s':>12}")
    rates = {}
    for name, count, fn in rows:
        t = median_s(fn, repeats)
        rates[name] = count / t
        print(f"  {name:<30}{t:>10.4f}{count / t:>12.1f}")
    # the protocol's real-set size: MMD cost grows with the square of the set size
    big = np.concatenate([hists] * max(1, 2000 // n_scans))[:2000]
    big = big + rng.poisson(0.05, big.shape)
    t = median_s(lambda: bev_mmd(big[:1000], big[1000:]), 1)
    print(f"  {'R2Flow MMD, 1000 vs 1000':<30}{t:>10.4f}{2000 / t:>12.1f}")
    return rates


def bench_frechet(repeats: int, scipy_4096: bool, rng: np.random.Generator) -> dict:
    print("Frechet distance from (mu, S) pairs (samples = 2 x dims, full-rank covariances)")
    print(f"  {'dims':>6}{'ours s':>10}{'scipy s':>10}{'ratio':>9}{'rel. diff':>12}")
    times = {}
    for d in (512, 1808, 4096):
        a = rng.standard_normal((2 * d, d)) @ (rng.standard_normal((d, d)) / np.sqrt(d))
        b = rng.standard_normal((2 * d, d)) * 1.3 + 0.1
        mu1, s1 = feature_statistics(a)
        mu2, s2 = feature_statistics(b)
        ours_value = frechet_distance(mu1, s1, mu2, s2)
        reps = repeats if d < 4096 else max(1, repeats // 2)
        ours = median_s(lambda: frechet_distance(mu1, s1, mu2, s2), reps)
        if d < 4096 or scipy_4096:
            ref_value = scipy_frechet(mu1, s1, mu2, s2)
            ref = median_s(lambda: scipy_frechet(mu1, s1, mu2, s2), 1 if d > 512 else reps)
            diff = abs(ours_value - ref_value) / abs(ref_value)
            times[d] = {"ours_s": ours, "scipy_s": ref}
            print(f"  {d:>6}{ours:>10.3f}{ref:>10.3f}{ref / ours:>9.1f}{diff:>12.2e}")
        else:
            print(f"  {d:>6}{ours:>10.3f}{'-':>10}{'-':>9}{'-':>12}")
            times[d] = {"ours_s": ours}
    print("Frechet distance from features, fewer samples than dims (Gram route)")
    for n, d in ((2000, 4096), (1000, 1808)):
        a = rng.standard_normal((n, d))
        b = rng.standard_normal((n, d)) * 1.1
        t = median_s(lambda: frechet_from_features(a, b), repeats)
        print(f"  {n} vs {n} samples, {d} dims: {t:.3f} s")
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=int, default=200, help="scans in the feature-free benchmark")
    ap.add_argument("--pool", type=int, default=20, help="distinct synthetic scans cycled through")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=str, default=None, help="BLAS threads (set before numpy loads)")
    ap.add_argument("--scipy-4096", action="store_true", help="also time scipy's sqrtm at 4096-d (minutes)")
    ap.add_argument("--skip-bev", action="store_true")
    ap.add_argument("--skip-frechet", action="store_true")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"BLAS threads: {os.environ.get('OPENBLAS_NUM_THREADS', 'default')}; cpus: {os.cpu_count()}")
    rows, figures = [], {}
    if not args.skip_bev:
        rates = figures["bev_scans_per_s"] = bench_bev(args.scans, args.repeats, args.pool, rng)
        rows.append({"what": "BEV histograms / JSD / MMD (R2Flow's, 100 x 100)",
                     "median": " / ".join(_rate(rates[k]) for k in ("BEV histograms (100x100)", "R2Flow JSD (from hists)",
                                                                     "R2Flow MMD (from hists)")) + " scans/s"})
    if not args.skip_frechet:
        times = figures["frechet_s"] = bench_frechet(args.repeats, args.scipy_4096, rng)
        scipy = [f"{t['scipy_s']:.2g}" for t in times.values() if "scipy_s" in t]
        rows.append({"what": "Frechet distance " + " / ".join(str(d) for d in times) + " dims",
                     "median": " / ".join(f"{t['ours_s']:.2g}" for t in times.values()) + " s"
                               + (f" (scipy sqrtm: {' / '.join(scipy)} s)" if scipy else ""),
                     "target": "seconds at 4096-d"})
    bench_record.write(args.out, rows, figures)


def _rate(per_s: float) -> str:
    return f"{per_s / 1e3:.0f}k" if per_s >= 1e4 else f"{per_s:.0f}"


if __name__ == "__main__":
    main()
