"""Precision-recall curves and the AP table of a Pi3DET experiment (one figure per target)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


COLORS = {"supervised-only": "#8c8c8c", "GDA": "#1f77b4"}


def pr_figure(panels: list[dict], out: str | Path, title: str = "") -> None:
    """A row of precision-recall panels plus a table of 3D AP (R11 / R40 at IoU 0.5), written atomically.

    Each panel: ``{"title", "series": {label: {"precision": [41 values at recall i/40], "r11", "r40"}}}``.
    """
    from omnilidar.io.figure import plt, save_figure

    if not panels:
        raise ValueError("no panels to draw")
    fig = plt.figure(figsize=(4.2 * len(panels), 6.2))
    grid = fig.add_gridspec(2, len(panels), height_ratios=[3, 1.4])
    rows = []
    for k, panel in enumerate(panels):
        ax = fig.add_subplot(grid[0, k])
        for label, s in panel["series"].items():
            precision = np.asarray(s["precision"], np.float64)
            if precision.size:
                recall = np.linspace(0, 1, precision.size)
                ax.step(recall, precision, where="post", color=COLORS.get(label), label=f"{label} (R11 {s['r11']:.2f})")
            rows.append([panel["title"], label, f"{s['r11']:.2f}", f"{s['r40']:.2f}"])
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("recall position")
        ax.set_ylabel("precision")
        ax.set_title(panel["title"], fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    table_ax = fig.add_subplot(grid[1, :])
    table_ax.axis("off")
    table = table_ax.table(cellText=rows, colLabels=["run", "training", "3D AP R11@0.5", "3D AP R40@0.5"],
                           loc="center", cellLoc="center")
    table.auto_set_font_size(False)
    table.set_fontsize(7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, out, dpi=110)


def label_fraction_figure(results: list[dict], out: str | Path, metric: str = "3d_R11@0.5") -> None:
    """Car AP against the real-label fraction: one panel per platform and detector, supervised-only
    and GDA, the platform's box labeler as a line. ``results``: pi3det-result documents."""
    from omnilidar.io.figure import plt, save_figure

    if not results:
        raise ValueError("no Pi3DET results to draw")
    platforms = sorted({r["platform"] for r in results})
    detectors = sorted({d for r in results for d in r["runs"]})
    fig, axes = plt.subplots(len(platforms), len(detectors), figsize=(4.6 * len(detectors), 3.4 * len(platforms)),
                             squeeze=False)
    for i, platform in enumerate(platforms):
        docs = sorted((r for r in results if r["platform"] == platform), key=lambda r: r["label_percent"])
        for j, detector in enumerate(detectors):
            ax = axes[i][j]
            pct = [r["label_percent"] for r in docs if detector in r["runs"]]
            for role, label in (("supervised_only", "supervised-only"), ("gda", "GDA")):
                ap = [r["runs"][detector][role]["ap"]["Car"][metric] for r in docs if detector in r["runs"]]
                ax.plot(pct, ap, "o-", color=COLORS[label], label=label)
            labeler = docs[-1]["labeler"]["val_ap"]["Car"][metric]
            ax.axhline(labeler, color="#d62728", ls="--", lw=1, label=f"box labeler ({labeler:.1f})")
            ax.set_xscale("log")
            ax.set_xticks(pct, [str(p) for p in pct])
            ax.set_xlabel("real labels (%)")
            ax.set_ylabel(f"Car {metric.replace('_', ' ')} (%)")
            ax.set_title(f"{platform}, {detector}", fontsize=9)
            ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
