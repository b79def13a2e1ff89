"""Figure of results/data_summary.json: every dataset's scene statistics beside real KITTI."""

from __future__ import annotations

from pathlib import Path

import numpy as np



def plot_data_summary(summary: dict, path: str | Path) -> None:
    from omnilidar.io.figure import plt, save_figure

    groups = summary["groups"]
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))

    ax = axes[0, 0]
    names = list(groups)
    means = [groups[n]["points_per_scan"]["mean"] / 1000 for n in names]
    ax.barh(names, means, color="tab:blue")
    ax.set_xlabel("points per scan (thousands, mean)")
    ax.set_title("Points per scan")

    ax = axes[0, 1]
    for n, g in groups.items():
        edges = g["range_edges_m"]
        centres = [f"{a:g}-{b:g}" for a, b in zip(edges[:-1], edges[1:])]
        ax.plot(centres, g["range_fraction"], marker="o", label=n, lw=2.5 if n.startswith("real") else 1.2)
    ax.set_xlabel("range bin (m)")
    ax.set_ylabel("share of points")
    ax.set_title("Range distribution")
    ax.legend(fontsize=7)

    ax = axes[1, 0]
    for n, g in groups.items():
        edges = np.asarray(g["elevation_edges_deg"])
        ax.plot(0.5 * (edges[1:] + edges[:-1]), g["elevation_fraction"], label=n,
                lw=2.5 if n.startswith("real") else 1.2)
    ax.set_xlabel("elevation (deg)")
    ax.set_ylabel("share of points")
    ax.set_title("Elevation profile (row occupancy)")
    ax.legend(fontsize=7)

    ax = axes[1, 1]
    published = summary["published_semantickitti_class_fraction"]
    ours = groups.get("semantickitti", {}).get("class_fraction") or {}
    classes = [c for c in published if c != "unlabeled"]
    x = np.arange(len(classes))
    ax.bar(x - 0.2, [published[c] for c in classes], 0.4, label="SemanticKITTI (published)")
    ax.bar(x + 0.2, [ours.get(c, 0.0) for c in classes], 0.4, label="this run's semantickitti")
    ax.set_xticks(x, classes, rotation=70, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("share of labelled points")
    ax.set_title("Class frequencies")
    ax.legend(fontsize=7)

    sources = ", ".join(f"{k}: {v}" for k, v in summary["data_source"].items())
    fig.suptitle(f"Scene statistics ({sources})")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
