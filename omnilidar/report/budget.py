"""What GDA gains for the generator's training compute (results/gda_budget.json).

Each budget is a generator trained that many iterations, its samples pseudo-labelled and
trained into the decomposition's regime with several seeds. Gains are taken seed by seed
against the decomposition's supervised-only row (same seeds), beside the gain of the same
number of real scans under the same labeler (``real_pseudo``): the level a perfect generator
would reach with this labeler. Where the measured points do not reach a level, a least-squares
line of every seed's gain against log10(CPU-minutes) says where the trend would, but only when
it rises by more than two standard errors of its slope: a line within the seeds' noise of flat
places no crossing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.downstream.seg.experiments import seed_statistics
from omnilidar.errors import InputError
from omnilidar.report.compute_trend import fit_line
from omnilidar.report.decomposition import paired_difference

LEVELS = ("supervised_only", "real_pseudo")  # gain 0, and the gain of pseudo-labelled real scans


def budget_record(iterations: int, generator: dict, quality: dict, runs: list[dict], supervised: dict,
                  real_pseudo: dict, evalset: str = "val") -> dict:
    """One budget: its generator's cost, its samples' quality and its runs' gains, seed-paired."""
    stats = seed_statistics(runs, evalset)
    if stats["seeds"] != supervised["seeds"]:
        raise InputError(runs[0]["_path"], f"budget {iterations}: seeds {stats['seeds']} differ from the "
                                           f"supervised-only row's {supervised['seeds']}")
    cpu = generator.get("train_cpu_seconds")
    if cpu is None:
        raise InputError(generator["path"], "records no train_cpu_seconds (trained before the budget study "
                                            "existed): retrain it")
    return {
        "iterations": int(iterations), "generator": generator["path"],
        "generator_iterations": generator.get("iterations"), "loss_weighting": generator.get("loss_weighting"),
        "prior": generator.get("prior"),
        "train_cpu_minutes": cpu / 60.0, "train_wall_minutes": generator.get("train_seconds", 0.0) / 60.0,
        "quality": quality["metrics"], "quality_scans": quality["n_generated"],
        **stats,
        "gain_over_supervised": paired_difference(stats["miou"], supervised["miou"]),
        "gain_over_real_pseudo": paired_difference(stats["miou"], real_pseudo["miou"]),
    }


def trend(budgets: list[dict], levels: dict[str, float]) -> dict:
    """Least-squares line of every seed's gain (a budget's mean where it records no seeds) against
    log10(CPU-minutes), and per level (a gain over supervised-only) the first measured budget that
    reaches it and, when the line rises beyond two standard errors, where the line would; where a level
    is not reached, also the earliest budget the seeds allow (the slope plus two standard errors)."""
    xs, ys = [], []
    for b in budgets:
        gains = b["gain_over_supervised"].get("per_seed") or [b["gain_over_supervised"]["mean"]]
        xs += [np.log10(b["train_cpu_minutes"])] * len(gains)
        ys += list(gains)
    slope, intercept, error = fit_line(np.asarray(xs), np.asarray(ys, dtype=float))
    flat = 1e-9  # slopes below this are rounding noise of an exactly level line
    rises = slope > max(2 * error if error is not None else 0.0, flat)
    steepest = slope + 2 * error if error is not None else None  # the fastest rise the seeds allow
    centre = (float(np.mean(xs)), float(np.mean(ys)))
    per_iteration = float(np.median([b["train_cpu_minutes"] / b["iterations"] for b in budgets]))
    out = {"fit": {"model": "seed gain = intercept + slope * log10(CPU-minutes)", "points": len(xs),
                   "slope_per_decade": slope, "slope_std_error": error, "steepest_slope_per_decade": steepest,
                   "intercept": intercept, "rises": bool(rises)}, "crossings": {}}
    for name, level in levels.items():
        reached = [b for b in budgets if b["gain_over_supervised"]["mean"] >= level]
        cross = {"level_gain": level, "first_measured_budget": reached[0]["iterations"] if reached else None,
                 "first_measured_cpu_minutes": reached[0]["train_cpu_minutes"] if reached else None}
        if not reached and steepest is not None and steepest > flat:
            # Earliest crossing the data allow: the line through the points' centre at the steepest slope.
            earliest = float(10 ** min(centre[0] + (level - centre[1]) / steepest, 300.0))
            cross["earliest_cpu_minutes"] = earliest
            cross["earliest_iterations"] = int(round(earliest / per_iteration))
        if rises:
            minutes = float(10 ** ((level - intercept) / slope))
            cross["trend_cpu_minutes"] = minutes
            cross["trend_iterations"] = int(round(minutes / per_iteration))
        else:
            cross["trend_cpu_minutes"] = cross["trend_iterations"] = None
            if slope > 0:
                cross["note"] = (f"the gain does not rise measurably in the measured range (slope "
                                 f"{100 * slope:.2f} +- {100 * error:.2f} points per decade, within two standard "
                                 f"errors of flat): no crossing predicted")
            else:
                cross["note"] = "the gain does not rise with the budget in the measured range: no crossing predicted"
        out["crossings"][name] = cross
    return out


def budget_figure(path: str | Path, doc: dict) -> None:
    """Left: the GDA gain over supervised-only against the generator's training CPU-minutes (seed dots,
    mean +- std, the fitted trend), with supervised-only (0) and pseudo-labelled real scans as levels.
    Right: each budget's sample quality. Written atomically as PNG."""
    from omnilidar.io.figure import plt, save_figure

    from omnilidar.report.log_axis import readable_log_x

    budgets = doc["budgets"]
    metrics = list(budgets[0]["quality"])
    fig, axes = plt.subplots(1, 1 + len(metrics), figsize=(5.6 + 3.0 * len(metrics), 4.2), squeeze=False,
                             gridspec_kw={"width_ratios": [2.0] + [1.0] * len(metrics)})
    ax = axes[0][0]
    x = np.asarray([b["train_cpu_minutes"] for b in budgets])
    means = np.asarray([100 * b["gain_over_supervised"]["mean"] for b in budgets])
    stds = np.asarray([100 * (b["gain_over_supervised"]["std"] or 0.0) for b in budgets])
    ax.errorbar(x, means, yerr=stds, fmt="o-", color="#1f77b4", capsize=4, label="GDA (generated scans)")
    for b in budgets:
        seeds = [100 * v for v in b["gain_over_supervised"]["per_seed"]]
        ax.plot(np.full(len(seeds), b["train_cpu_minutes"]), seeds, "k.", ms=4)
        ax.annotate(f"{b['iterations']} it.", (b["train_cpu_minutes"], 100 * b["gain_over_supervised"]["mean"]),
                    textcoords="offset points", xytext=(4, 6), fontsize=7)
    ax.axhline(0.0, color="#7f7f7f", ls="--", lw=1, label="supervised only")
    rp = doc["reference"]["real_pseudo_gain"]
    ax.axhline(100 * rp["mean"], color="#2ca02c", ls="--", lw=1, label="+N real, labeler's labels")
    if rp["std"]:
        ax.axhspan(100 * (rp["mean"] - rp["std"]), 100 * (rp["mean"] + rp["std"]), color="#2ca02c", alpha=0.1)
    fit = doc["trend"]["fit"]
    reach = [c["trend_cpu_minutes"] for c in doc["trend"]["crossings"].values() if c.get("trend_cpu_minutes")]
    hi = max([x.max(), *[m for m in reach if m < 1e4 * x.max()]])
    line = np.geomspace(x.min(), hi, 50)
    ax.plot(line, 100 * (fit["intercept"] + fit["slope_per_decade"] * np.log10(line)), ":", color="#1f77b4",
            lw=1, label="trend (fit on seeds)")
    ax.set_xscale("log")
    readable_log_x(ax)
    ax.set_xlabel("generator training (CPU-minutes)")
    ax.set_ylabel("val mIoU gain over supervised only (points)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    setup = doc["setup"]
    generator = ", ".join(f"{key.replace('_', ' ')} {'/'.join(setup[key])}" for key in ("loss_weighting", "prior")
                          if setup.get(key))
    ax.set_title(f"{setup['backbone']}, {setup['percent']:g} % labels + N = {setup['scans']} "
                 f"({len(doc['reference']['seeds'])} seeds, seed-paired)" + (f"\ngenerator: {generator}" if generator else ""),
                 fontsize=9)
    for ax, metric in zip(axes[0][1:], metrics):
        values = [b["quality"][metric] for b in budgets]
        keep = [i for i, v in enumerate(values) if v is not None]
        ax.plot(x[keep], [values[i] for i in keep], "s-", color="#9467bd")
        ax.set_xscale("log")
        readable_log_x(ax, max_ticks=3)
        ax.set_xlabel("CPU-minutes")
        ax.set_title(f"{metric} vs held-out real (lower is better)", fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
