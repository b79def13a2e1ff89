"""What accuracy costs in time: each effect's numerical knobs against time per scan.

Every effect module measures its own curve (``accuracy_time_curve``: one knob
varied at a time, errors of scan statistics against a high-fidelity setting,
averaged over seeds). The modules name their columns differently (``time_s``,
``seconds`` or ``apply_s``; ``err_*``), so this module normalises the rows, marks
the chosen defaults (``DEFAULT_FIDELITY``) and plots error against time per
knob, one panel per effect, on the effect's primary statistic.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from omnilidar.domains.spec import effect_module
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec

TIME_KEYS = ("time_s", "seconds", "apply_s")
# The statistic each panel plots (the one the effect exists to produce).
PRIMARY_ERROR = {
    "fog": "err_fog_fraction",
    "snow": "err_weather",
    "rain": "err_frac_rain",
    "wet_ground": "err_lost",
    "beam_reduction": "err_keep_mismatch",
    "beam_missing": "err_ring_mismatch",
}


def study_severity(effect: str, severity: str) -> str:
    """``severity`` if the effect has it, else the middle (lower middle) of its named severities."""
    names = list(effect_module(effect).SEVERITIES)
    return severity if severity in names else names[(len(names) - 1) // 2]


def normalise_rows(effect: str, rows: list[dict]) -> list[dict]:
    """Rows as {knob, value, time_s, errors {err_*: float}, is_default, extra}."""
    module = effect_module(effect)
    out = []
    for row in rows:
        t = next((float(row[k]) for k in TIME_KEYS if k in row), float("nan"))
        errors = {k: float(v) for k, v in row.items() if k.startswith("err_")}
        default = row.get("is_default", module.DEFAULT_FIDELITY.get(row["knob"]) == row["value"])
        extra = {k: v for k, v in row.items()
                 if k not in ("knob", "value", "is_default", *TIME_KEYS) and not k.startswith("err_")}
        out.append({"knob": row["knob"], "value": row["value"], "time_s": t, "errors": errors,
                    "is_default": bool(default), "extra": extra})
    return out


def tradeoff_study(scan: Scan, sensor: SensorSpec, effects: list[str], severity: str, seeds: list[int],
                   progress: bool = True) -> dict:
    """{effect: {severity, primary_error, default_fidelity, levels, wall_s, rows}} for each effect."""
    from tqdm import tqdm

    result = {}
    for effect in tqdm(effects, desc="tradeoff", file=sys.stderr, disable=not progress):
        module = effect_module(effect)
        sev = study_severity(effect, severity)
        t0 = time.perf_counter()
        rows = normalise_rows(effect, module.accuracy_time_curve(scan, sensor, sev, list(seeds)))
        errors = rows[0]["errors"] if rows else {}
        primary = PRIMARY_ERROR.get(effect)
        if primary not in errors:
            primary = sorted(errors)[0] if errors else None
        result[effect] = {
            "severity": sev,
            "primary_error": primary,
            "default_fidelity": dict(module.DEFAULT_FIDELITY),
            "levels": {k: list(v) for k, v in module.FIDELITY_LEVELS.items()},
            "wall_s": time.perf_counter() - t0,
            "rows": rows,
        }
    return result


def plot_tradeoff(result: dict, path: str | Path) -> None:
    """Error of the primary statistic vs time per scan, a line per knob, defaults starred."""
    from omnilidar.io.figure import plt, save_figure
    from matplotlib.ticker import NullFormatter


    n = max(len(result), 1)
    cols = min(n, 3)
    rows_n = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 3.8 * rows_n), squeeze=False)
    for ax, (effect, entry) in zip(axes.ravel(), result.items()):
        key = entry["primary_error"]
        knobs = dict.fromkeys(r["knob"] for r in entry["rows"])
        for k, knob in enumerate(knobs):
            pts = [r for r in entry["rows"] if r["knob"] == knob]
            t = [r["time_s"] for r in pts]
            e = [r["errors"].get(key, np.nan) for r in pts]
            ax.plot(t, e, "o-", color=f"C{k}", label=knob, ms=4)
            for r, ti, ei in zip(pts, t, e):
                ax.annotate(str(r["value"]), (ti, ei), fontsize=6, xytext=(2, 2), textcoords="offset points")
                if r["is_default"]:
                    ax.plot(ti, ei, "*", color=f"C{k}", ms=14, mec="k")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_yscale("symlog", linthresh=1e-4)
        ax.set_ylim(bottom=0.0)
        ax.set(title=f"{effect} ({entry['severity']})", xlabel="seconds per scan", ylabel=key or "error")
        ax.legend(fontsize=7, title="knob (star = default)", title_fontsize=7)
    for ax in axes.ravel()[len(result):]:
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
