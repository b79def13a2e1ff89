"""Writing a figure: the one place figures are saved (atomically, then closed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window (cluster nodes have no display)
import matplotlib.pyplot as plt  # noqa: E402

from omnilidar.io.atomic import atomic_path  # noqa: E402


def save_figure(fig, path: str | Path, dpi: int = 100) -> None:
    """Write ``fig`` to ``path`` atomically (format from the suffix, PNG without one) and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
