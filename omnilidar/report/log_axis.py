"""Readable tick labels on logarithmic axes.

Matplotlib labels minor ticks of a log axis that spans less than about one
decade (``LogFormatter``'s ``minor_thresholds``), so a short seconds axis gets
a crowded row of overlapping labels. :func:`readable_log_x` puts a log x axis
on a few round ticks (1-2-5, 1-2-3-5, ... times a power of ten) labelled as
plain numbers, and never labels minor ticks.
"""

from __future__ import annotations

import numpy as np

# Tick mantissas from coarse to fine: the coarsest set giving enough ticks wins.
MANTISSA_SETS = ((1.0,), (1.0, 2.0, 5.0), (1.0, 2.0, 3.0, 5.0), (1.0, 1.5, 2.0, 3.0, 5.0, 7.0),
                 (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0))


def nice_log_ticks(lo: float, hi: float, max_ticks: int = 5, min_ticks: int = 3) -> list[float]:
    """Round numbers in [lo, hi] for a log axis: those of the coarsest mantissa set
    (1; 1-2-5; 1-2-3-5; ...) that gives ``min_ticks``, thinned evenly in log space to
    ``max_ticks``. When fewer than two round numbers fit, three log-spaced values
    rounded to the fewest significant digits that keep them apart."""
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo <= 0 or hi <= lo:
        raise ValueError(f"need 0 < lo < hi, got {lo}, {hi}")
    max_ticks = max(2, int(max_ticks))
    decades = np.arange(np.floor(np.log10(lo)), np.ceil(np.log10(hi)) + 1)
    inside = np.zeros(0)
    for mantissas in MANTISSA_SETS:
        # Parsed from decimal text, so that 6 x 0.1 is exactly the float 0.6.
        candidates = np.unique([float(f"{m:g}e{int(d)}") for d in decades for m in mantissas])
        inside = candidates[(candidates >= lo * (1 - 1e-9)) & (candidates <= hi * (1 + 1e-9))]
        if len(inside) >= min_ticks:
            break
    if len(inside) < 2:
        # No two round numbers fit: three interior points spread in log space (not the
        # axis ends, whose labels get clipped), with as few significant digits as keep
        # them inside and distinct.
        spread = np.geomspace(lo, hi, 5)[1:4]
        for digits in range(2, 8):
            inside = np.unique([float(f"{v:.{digits}g}") for v in spread])
            if len(inside) == 3 and inside[0] >= lo and inside[-1] <= hi:
                break
    if len(inside) > max_ticks:
        # Evenly spaced in log space: the candidate nearest each of max_ticks targets.
        targets = np.linspace(np.log10(inside[0]), np.log10(inside[-1]), max_ticks)
        picks = np.unique([int(np.argmin(np.abs(np.log10(inside) - t))) for t in targets])
        inside = inside[picks]
    return [float(v) for v in inside]


def tick_labels(ticks: list[float]) -> list[str]:
    """Plain-number labels of ``ticks`` (0.25, 3, 1.5e+04) with the fewest significant
    digits (at least three) that tell them apart."""
    for digits in range(3, 10):
        labels = [f"{t:.{digits}g}" for t in ticks]
        if len(set(labels)) == len(labels):
            return labels
    return [repr(float(t)) for t in ticks]


def readable_log_x(ax, max_ticks: int = 5) -> None:
    """Log-scale the x axis of ``ax`` with readable labels; call after plotting.

    Spans of a decade or more keep Matplotlib's decade ticks (labelled as plain
    numbers); shorter spans get :func:`nice_log_ticks`. Minor ticks stay unlabelled.
    """
    from matplotlib.ticker import FixedFormatter, FixedLocator, FuncFormatter, NullFormatter

    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _pos=None: f"{value:.3g}"))
    lo, hi = ax.get_xlim()
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo <= 0 or hi <= lo or np.log10(hi / lo) >= 1.0:
        return
    ticks = nice_log_ticks(lo, hi, max_ticks)
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(FixedFormatter(tick_labels(ticks)))
    ax.set_xlim(lo, hi)
