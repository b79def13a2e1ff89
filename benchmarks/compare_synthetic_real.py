"""Realism report: synthetic KITTI-like scans beside real KITTI scans.

    python benchmarks/compare_synthetic_real.py FIGURE.png [--scenes 4] [--scans-per-scene 2] [--out FILE]

Real data: the three full HDL-64E sweeps in OMNILIDAR_REAL_DATA (two KITTI
object scans and SemanticKITTI 00/000000). Those have no per-point labels (the
labelled sample there has only 50 points), so class frequencies are compared
with the published SemanticKITTI training-set statistics instead: the
``content`` ratios of the official semantic-kitti-api config
(config/semantic-kitti.yaml), summed per learning class.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import bench_record  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from real_samples import real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
REAL_SCANS = ("kitti_object/velodyne/000000.bin", "kitti_object/velodyne/000001.bin",
              "semantickitti/sequences/00/velodyne/000000.bin")

# SemanticKITTI training set, share of points per learning class (official `content`
# ratios, raw ids summed per class; unlabeled/outlier/other-structure/other-object
# are the remaining ~3.2 %).
SEMANTICKITTI_CLASS_SHARE = {
    "car": 0.0426, "bicycle": 0.0002, "motorcycle": 0.0004, "truck": 0.0022, "other-vehicle": 0.0019,
    "person": 0.0003, "bicyclist": 0.0001, "motorcyclist": 0.0000, "road": 0.1988, "parking": 0.0147,
    "sidewalk": 0.1439, "other-ground": 0.0039, "building": 0.1327, "fence": 0.0724, "vegetation": 0.2668,
    "trunk": 0.0060, "terrain": 0.0781, "pole": 0.0029, "traffic-sign": 0.0006,
}


def main() -> None:
    parser = argparse.ArgumentParser(description="synthetic vs real KITTI statistics")
    parser.add_argument("figure", type=Path, help="where to save the comparison figure (.png)")
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--scans-per-scene", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    bench_record.out_arg(parser)
    args = parser.parse_args()
    real_scans = real_files_or_exit(REAL_SCANS)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omnilidar.config import section_defaults
    from omnilidar.data.synthetic.sequence import shard_entropy, simulate_sequence
    from omnilidar.data.synthetic.statistics import scan_statistics
    from omnilidar.io.atomic import atomic_path
    from omnilidar.io.semantickitti import read_scan

    settings = section_defaults("synthetic")
    entropy = shard_entropy(args.seed, "compare", "kitti")
    synth = []
    for k in range(args.scenes):
        _, scans = simulate_sequence(settings, entropy, k, "kitti_hdl64e", "vehicle", args.scans_per_scene, 10.0)
        synth.extend(scans)
    s = scan_statistics(synth)
    r = scan_statistics([read_scan(p) for p in real_scans])

    print(f"synthetic: {s['num_scans']} scans from {args.scenes} scenes; real: {r['num_scans']} KITTI sweeps")
    edges = s["range_edges_m"]
    bands = [f"{edges[i]:g}-{edges[i + 1]:g} m" for i in range(len(edges) - 1)]
    quantities = [("points per scan (mean)", s["points_per_scan"]["mean"], r["points_per_scan"]["mean"], ".0f"),
                  ("exact-zero remission fraction", s["zero_remission_fraction"], r["zero_remission_fraction"], ".3f")]
    for key, what in (("range_fraction", "share of points"), ("zero_remission_by_range", "zero-remission share"),
                      ("mean_remission_by_range", "mean remission")):
        quantities += [(f"{what}, range {band}", s[key][i], r[key][i], ".3f") for i, band in enumerate(bands)]
    cf = s["class_fraction"] or {}
    quantities += [(f"class share {name} (real: published SemanticKITTI)", cf.get(name, 0.0), ref, ".4f")
                   for name, ref in SEMANTICKITTI_CLASS_SHARE.items()]
    columns = ["quantity", f"synthetic ({s['num_scans']} scans)", f"real KITTI ({r['num_scans']} sweeps)"]
    rows = []
    for what, synthetic, real, fmt in quantities:
        rows.append(dict(zip(columns, (what, format(synthetic, fmt), format(real, fmt)))))
        print(f"{what:<52}{format(synthetic, fmt):>12}{format(real, fmt):>12}")

    fig, ax = plt.subplots(2, 2, figsize=(12, 8))
    centers = [f"{edges[i]:g}-{edges[i + 1]:g}" for i in range(len(edges) - 1)]
    x = np.arange(len(centers))
    ax[0, 0].bar(x - 0.2, s["range_fraction"], 0.4, label="synthetic")
    ax[0, 0].bar(x + 0.2, r["range_fraction"], 0.4, label="real KITTI")
    ax[0, 0].set_xticks(x, centers)
    ax[0, 0].set(title="range distribution", xlabel="range (m)", ylabel="share of points")
    ax[0, 0].legend()
    ax[0, 1].plot(x, s["zero_remission_by_range"], "o-", label="synthetic zero share")
    ax[0, 1].plot(x, r["zero_remission_by_range"], "s-", label="real zero share")
    ax[0, 1].plot(x, s["mean_remission_by_range"], "o--", label="synthetic mean remission")
    ax[0, 1].plot(x, r["mean_remission_by_range"], "s--", label="real mean remission")
    ax[0, 1].set_xticks(x, centers)
    ax[0, 1].set(title="remission vs range", xlabel="range (m)")
    ax[0, 1].legend(fontsize=8)
    e = np.asarray(s["elevation_edges_deg"])
    mid = 0.5 * (e[1:] + e[:-1])
    ax[1, 0].plot(mid, s["elevation_fraction"], "o-", label="synthetic")
    ax[1, 0].plot(mid, r["elevation_fraction"], "s-", label="real KITTI")
    ax[1, 0].set(title="elevation (row occupancy) profile", xlabel="elevation (deg)", ylabel="share of points")
    ax[1, 0].legend()
    names = list(SEMANTICKITTI_CLASS_SHARE)
    xc = np.arange(len(names))
    ax[1, 1].bar(xc - 0.2, [cf.get(n, 0.0) for n in names], 0.4, label="synthetic")
    ax[1, 1].bar(xc + 0.2, [SEMANTICKITTI_CLASS_SHARE[n] for n in names], 0.4, label="SemanticKITTI (published)")
    ax[1, 1].set_xticks(xc, names, rotation=70, fontsize=7)
    ax[1, 1].set(title="class frequencies", ylabel="share of points")
    ax[1, 1].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(args.figure) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    print(f"\nfigure: {args.figure}")
    bench_record.write(args.out, rows, {"quantities": {what: [float(a), float(b)] for what, a, b, _ in quantities},
                                        "scenes": args.scenes, "scans_per_scene": args.scans_per_scene,
                                        "seed": args.seed}, columns=columns)


if __name__ == "__main__":
    main()
