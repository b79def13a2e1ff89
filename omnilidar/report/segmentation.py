"""Per-class IoU bar figures of the segmentation experiments (supervised-only vs GDA)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


COLORS = ("#8c8c8c", "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728")


def iou_bars(panels: list[dict], out: str | Path, title: str = "") -> None:
    """One bar chart per panel, written atomically as PNG.

    Each panel: ``{"title": str, "classes": [names], "series": {label: {"iou": {class: fraction},
    "miou": fraction}}}``; bars are percent, the legend carries each series' mIoU. A series over
    several seeds also has ``iou_std``, ``miou_std`` and ``seeds``: error bars and mean +- std.
    """
    from omnilidar.io.figure import plt, save_figure

    if not panels:
        raise ValueError("no panels to draw")
    fig, axes = plt.subplots(len(panels), 1, figsize=(12, 3.2 * len(panels)), squeeze=False)
    for ax, panel in zip(axes[:, 0], panels):
        classes = list(panel["classes"])
        series = panel["series"]
        x = np.arange(len(classes))
        width = 0.8 / max(1, len(series))
        for k, (label, s) in enumerate(series.items()):
            values = [100.0 * float(s["iou"].get(c, 0.0)) for c in classes]
            errors = [100.0 * float(s["iou_std"].get(c, 0.0)) for c in classes] if "iou_std" in s else None
            miou = (f"mIoU {100 * s['miou']:.1f} +- {100 * s['miou_std']:.1f}, {s['seeds']} seeds" if errors
                    else f"mIoU {100 * s['miou']:.1f}")
            ax.bar(x + (k - (len(series) - 1) / 2) * width, values, width, yerr=errors, capsize=2,
                   color=COLORS[k % len(COLORS)], label=f"{label} ({miou})")
        ax.set_xticks(x, classes, rotation=45, ha="right", fontsize=8)
        ax.set_ylabel("IoU (%)")
        ax.set_ylim(0, 100)
        ax.set_title(panel["title"], fontsize=10)
        ax.legend(fontsize=8, loc="upper right")
        ax.grid(axis="y", alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
