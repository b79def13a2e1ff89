"""Precision-recall curves and the AP table of a Pi3DET experiment (one figure per target)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.io.atomic import atomic_path

COLORS = {"supervised-only": "#8c8c8c", "GDA": "#1f77b4"}


def pr_figure(panels: list[dict], out: str | Path, title: str = "") -> None:
    """A row of precision-recall panels plus a table of 3D AP (R11 / R40 at IoU 0.5), written atomically.

    Each panel: ``{"title", "series": {label: {"precision": [41 values at recall i/40], "r11", "r40"}}}``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
