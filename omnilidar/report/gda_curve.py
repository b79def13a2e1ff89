"""The GDA curve: downstream mIoU against the number of generated scans, and its compute.

Each point is one segmentor run (same backbone, label subset and seed) trained
on the real subset plus the first N generated scans of one domain; N = 0 is
the supervised-only run. What a point cost, in seconds:

    train_seconds         the run's own recorded training time (train.seconds)
    sampling_seconds      N x seconds per scan of the sample shards
    pseudo_label_seconds  N x seconds per scan of their pseudo-labelling
    total_seconds         the sum of the three

Seconds per scan of sampling come from each sample shard's ``timing.json``
(the sampling loop's seconds over the scans it generated; model loading, a
per-job constant, is left out); pseudo-labelling from the pseudo-label shards'
sidecars. The labeler's own training is a one-off cost shared by every point
and is reported apart (the result's timings).

A curve file (``results/gda_curve.json``) holds ``rows``, one per point and
sorted by ``generated_scans``; :func:`read_curve` checks one for other stages.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io.json_file import read_json

ROW_FIELDS = ("generated_scans", "miou", "train_seconds", "sampling_seconds", "total_seconds")
TOTAL_NOTE = ("total_seconds = train_seconds + sampling_seconds + pseudo_label_seconds; the labeler's one-off "
              "training (timings.labeler) and evaluation are not included")


def shard_scans(shard: str | Path) -> int:
    """Scans (``velodyne/*.bin``) in a sample shard."""
    velo = Path(shard) / "velodyne"
    if not velo.is_dir():
        raise InputError(shard, "sample shard has no velodyne/ folder")
    count = sum(1 for _ in velo.glob("*.bin"))
    if count == 0:
        raise InputError(velo, "sample shard holds no .bin scans")
    return count


def sampling_seconds_per_scan(shards: list[str | Path]) -> tuple[float, int]:
    """(seconds per generated scan, scans in the shards) from each sample shard's own
    ``timing.json`` (written by ``omnilidar sample``: sampling seconds and scans it generated)."""
    from omnilidar.generator.sampling import TIMING_FILE

    if not shards:
        raise InputError(None, "no sample shards to measure the sampling time on")
    seconds, timed = 0.0, 0
    for shard in shards:
        path = Path(shard) / TIMING_FILE
        doc = read_json(path, f"sample shard has no {TIMING_FILE} (written by omnilidar sample)")
        try:
            s, n = float(doc["seconds"]), int(doc["scans"])
        except (KeyError, TypeError, ValueError):
            raise InputError(path, "not a sample timing file (needs 'seconds' and 'scans')") from None
        if not math.isfinite(s) or s < 0 or n < 0:
            raise InputError(path, f"seconds must be finite and >= 0 and scans >= 0, got {s}, {n}")
        seconds, timed = seconds + s, timed + n
    if timed == 0:
        raise InputError(shards[0], "the sample shards' timing files record no generated scan")
    return seconds / timed, sum(shard_scans(s) for s in shards)


def pseudo_label_seconds_per_scan(shards: list[str | Path]) -> tuple[float, float | None]:
    """(seconds per scan of the pseudo-label shards, from their sidecars' ``seconds`` and
    ``scans``; the labeler's one-off training seconds the first sidecar records, or None)."""
    seconds, scans, labeler = 0.0, 0, None
    for shard in shards:
        side = Path(shard) / "sidecar.json"
        doc = read_json(side, "pseudo-label shard has no sidecar.json")
        try:
            s, n = float(doc["seconds"]), len(doc["scans"])
        except (KeyError, TypeError, ValueError):
            raise InputError(side, "not a pseudo-label sidecar (needs 'seconds' and 'scans')") from None
        if not math.isfinite(s) or s < 0:
            raise InputError(side, f"seconds must be finite and >= 0, got {s}")
        seconds, scans = seconds + s, scans + n
        if labeler is None:
            train = (doc.get("labeler") or {}).get("train") or {}
            if isinstance(train.get("seconds"), (int, float)):
                labeler = float(train["seconds"])
    return (seconds / scans if scans else 0.0), labeler


def generated_count(ev: dict) -> int:
    """Generated scans a run took: 0 for supervised-only, else its --max-generated N."""
    info = ev["train"].get("info", {})
    if info.get("role") == "supervised_only":
        return 0
    count = info.get("max_generated")
    if info.get("role") != "gda" or not isinstance(count, int) or count < 1:
        raise InputError(ev.get("_path"), "not a run trained with --max-generated N (or supervised-only)")
    return count


def curve_rows(evaluations: list[dict], sampling_per_scan: float, pseudo_per_scan: float = 0.0) -> list[dict]:
    """One row per number of generated scans (``evaluate-segmentor`` documents), sorted by it.

    Every run must share backbone, dataset and label percent, and the GDA runs one
    domain. Several seeds per count give the row their mean mIoU (and training seconds),
    the sample standard deviation and every seed's value; every count must have run the
    same seeds, and two runs of one count and seed are an error.
    """
    if not evaluations:
        raise InputError(None, "no evaluations given")
    by_count: dict[int, dict[int, dict]] = {}
    setup = None
    for ev in evaluations:
        path = ev.get("_path")
        info = ev["train"].get("info", {})
        key = {"backbone": ev["model"]["backbone"], "dataset": info.get("dataset"), "percent": info.get("percent")}
        if setup is None:
            setup = key
        elif key != setup:
            raise InputError(path, f"run differs from the first one ({key} vs {setup}); a curve varies only "
                                   "the number of generated scans (and the seed)")
        if "val" not in ev["sets"]:
            raise InputError(path, "has no 'val' set")
        count = generated_count(ev)
        seeds = by_count.setdefault(count, {})
        if ev.get("seed") in seeds:
            raise InputError(path, f"a second run with {count} generated scans and seed {ev.get('seed')}")
        seeds[ev.get("seed")] = ev
    seed_sets = {count: sorted(runs) for count, runs in by_count.items()}
    if len({tuple(v) for v in seed_sets.values()}) > 1:
        raise InputError(None, f"the counts ran different seeds ({seed_sets}); a row's mean needs the same seeds")
    rows = {}
    for count, runs in by_count.items():
        docs = [runs[k] for k in sorted(runs)]
        first, mious = docs[0], [float(d["sets"]["val"]["miou"]) for d in docs]
        train_s = float(np.mean([float(d["train"]["seconds"]) for d in docs]))
        sampling = count * sampling_per_scan
        pseudo = count * pseudo_per_scan
        rows[count] = {
            "generated_scans": count,
            "trained_generated_scans": int(first["train"]["num_generated"]),
            "domains": list(first["train"].get("info", {}).get("domains", [])),
            "miou": float(np.mean(mious)),
            "miou_std": float(np.std(mious, ddof=1)) if len(docs) > 1 else None,
            "miou_per_seed": mious,
            "seeds": sorted(runs),
            "miou_nanmean": float(np.mean([float(d["sets"]["val"]["miou_nanmean"]) for d in docs])),
            "train_seconds": round(train_s, 2),
            "sampling_seconds": round(sampling, 2),
            "pseudo_label_seconds": round(pseudo, 2),
            "total_seconds": round(train_s + sampling + pseudo, 2),
            "iterations": first["train"]["iterations"],
            "checkpoint": first["checkpoint"],
        }
    domains = {d for r in rows.values() for d in r["domains"]}
    if len(domains) > 1:
        raise InputError(None, f"the GDA runs use different domains ({', '.join(sorted(domains))})")
    for r in rows.values():
        if not all(math.isfinite(r[k]) for k in ROW_FIELDS):
            raise InputError(r["checkpoint"], "run has a non-finite mIoU or time")
    return [rows[k] for k in sorted(rows)]


SERIES_ROLES = ("real_truth", "real_pseudo")  # curves of real pool scans beside the generated one


def series_rows(evaluations: list[dict]) -> dict[str, list[dict]]:
    """role -> rows (one per N = --max-pool, sorted) of the real series' runs: mean mIoU over the
    seeds, its sample standard deviation, every seed's value and the mean training seconds."""
    from omnilidar.downstream.seg.experiments import seed_statistics

    by_role: dict[str, dict[int, list[dict]]] = {}
    for ev in evaluations:
        info = ev["train"].get("info", {})
        count = info.get("max_pool")
        if info.get("role") not in SERIES_ROLES or not isinstance(count, int) or count < 1:
            raise InputError(ev.get("_path"), "not a run on the first N scans of a real pool (--max-pool N)")
        by_role.setdefault(info["role"], {}).setdefault(count, []).append(ev)
    out = {}
    for role, counts in by_role.items():
        rows = []
        for count in sorted(counts):
            docs = sorted(counts[count], key=lambda d: d["seed"])
            stats = seed_statistics(docs)
            rows.append({"scans": count, "miou": stats["miou_mean"], "miou_std": stats["miou_std"],
                         "miou_per_seed": stats["miou"], "seeds": stats["seeds"],
                         "train_seconds": round(float(np.mean([d["train"]["seconds"] for d in docs])), 2)})
        out[role] = rows
    return out


def read_curve(path: str | Path) -> dict:
    """A GDA curve file, checked: ``rows`` of finite numbers (``ROW_FIELDS``), sorted by
    generated scans, mIoU a fraction in [0, 1], seconds >= 0. Returns the document."""
    path = Path(path)
    doc = read_json(path, "GDA curve file not found (the gda_curve rule writes it)")
    rows = doc.get("rows") if isinstance(doc, dict) else None
    if not isinstance(rows, list) or not rows:
        raise InputError(path, "not a GDA curve: needs a non-empty list 'rows'")
    seen = set()
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise InputError(path, f"rows[{i}] is not an object")
        missing = [k for k in ROW_FIELDS if k not in row]
        if missing:
            raise InputError(path, f"rows[{i}] lacks {', '.join(missing)}")
        bad = [k for k in ROW_FIELDS if isinstance(row[k], bool) or not isinstance(row[k], (int, float))
               or not math.isfinite(row[k]) or row[k] < 0]
        if bad:
            raise InputError(path, f"rows[{i}].{bad[0]} must be a finite number >= 0, got {row[bad[0]]!r}")
        if row["generated_scans"] != int(row["generated_scans"]):
            raise InputError(path, f"rows[{i}].generated_scans must be a whole number, got {row['generated_scans']}")
        if row["miou"] > 1:
            raise InputError(path, f"rows[{i}].miou must be a fraction in [0, 1], got {row['miou']}")
        if row["generated_scans"] in seen:
            raise InputError(path, f"two rows with {row['generated_scans']} generated scans")
        seen.add(row["generated_scans"])
    doc["rows"] = sorted(rows, key=lambda r: r["generated_scans"])
    return doc


def draw_miou_vs_compute(ax, rows: list[dict], title: str = "") -> None:
    """mIoU (%) against total compute seconds (training + sampling + pseudo-labels), each
    point labelled with its number of generated scans; a log x axis with readable ticks
    when every total is positive."""
    from omnilidar.report.log_axis import readable_log_x

    x = [r["total_seconds"] for r in rows]
    y = [100.0 * r["miou"] for r in rows]
    ax.plot(x, y, "o-", color="#1f77b4")
    for r, xi, yi in zip(rows, x, y):
        ax.annotate(f"{int(r['generated_scans'])}", (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.margins(x=0.1, y=0.12)  # room for the labels of the end points
    if all(v > 0 for v in x):
        readable_log_x(ax)
    ax.set_xlabel("total compute (s)")
    ax.set_ylabel("val mIoU (%)")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=9)


def curve_figure(path: str | Path, doc: dict) -> None:
    """Three panels, written atomically as PNG: mIoU against generated scans, mIoU
    against total compute (points labelled with generated scans), and each point's
    compute split into training, sampling and pseudo-labelling."""
    from omnilidar.io.figure import plt, save_figure
    from matplotlib.ticker import MaxNLocator


    rows = doc["rows"]
    counts = [int(r["generated_scans"]) for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.8))
    ax = axes[0]
    spread = [100.0 * r["miou_std"] if r.get("miou_std") is not None else 0.0 for r in rows]
    ax.errorbar(counts, [100.0 * r["miou"] for r in rows], yerr=spread if any(spread) else None, fmt="o-",
                color="#1f77b4", capsize=3, label="generated (labeler's labels)")
    start = [r for r in rows if r["generated_scans"] == 0]  # supervised-only: where every series starts
    for role, label, color in (("real_truth", "real, true labels", "#2ca02c"),
                               ("real_pseudo", "real, labeler's labels", "#98df8a")):
        series = doc.get("real_series", {}).get(role)
        if not series:
            continue
        xs = [0] * len(start) + [r["scans"] for r in series]
        ys = [100.0 * r["miou"] for r in start + series]
        errs = [100.0 * (r.get("miou_std") or 0.0) for r in start + series]
        ax.errorbar(xs, ys, yerr=errs if any(errs) else None, fmt="s--", color=color, capsize=3, label=label)
    if doc.get("real_series"):
        ax.legend(fontsize=7)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("scans added")
    ax.set_ylabel("val mIoU (%)")
    ax.grid(alpha=0.3)
    seeds = len(rows[0].get("seeds") or [None])
    ax.set_title("mIoU vs scans added" + (f" (mean +- std over {seeds} seeds)" if seeds > 1 else " (one seed)"),
                 fontsize=9)
    draw_miou_vs_compute(axes[1], rows, "mIoU vs compute (training + sampling + pseudo-labels)")
    ax = axes[2]
    x = np.arange(len(rows))
    bottom = np.zeros(len(rows))
    for key, label, color in (("train_seconds", "training", "#1f77b4"), ("sampling_seconds", "sampling", "#ff7f0e"),
                              ("pseudo_label_seconds", "pseudo-labels", "#2ca02c")):
        values = np.array([float(r.get(key, 0.0)) for r in rows])
        ax.bar(x, values, 0.6, bottom=bottom, label=label, color=color)
        bottom += values
    ax.set_xticks(x, [str(c) for c in counts])
    ax.set_xlabel("generated scans added")
    ax.set_ylabel("seconds")
    ax.legend(fontsize=7)
    ax.set_title("compute per point", fontsize=9)
    setup = doc.get("setup", {})
    if setup:
        pct = setup.get("percent")
        labels = f"{pct:g} % labels" if isinstance(pct, (int, float)) else "labels"
        fig.suptitle(f"GDA curve: {setup.get('backbone')}, {labels}, {setup.get('domain')} samples "
                     f"({setup.get('dataset')})", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
