"""Fidelity report: what each effect does to KITTI-format scans, per severity.

For every effect and each of its named severities, on the given scans and seeds
(parameters are drawn per scan, e.g. fog's attenuation, as in the domains):

* fractions of the scan's points that are changed (kept, with a new position,
  intensity or label), lost, and turned into weather returns ("added": fog, snow
  and rain returns replace the beam's point, they are the added clutter);
* range and intensity distributions of the weather returns (histograms on fixed
  bins and quantiles);
* intensity shift of kept, non-weather points (physical 0..1 units);
* losses among zero-remission points (an anchor flaw: LISA loses them all);
* time per scan (the effect's apply; ground estimation separately).

Each effect's entry carries the anchors' measured behaviour from REFERENCE.md
section 4 and a note on what ours does differently, so the figure can be read
beside the anchors' numbers.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from omnilidar.data_source import record
from omnilidar.domains import ground as ground_estimation
from omnilidar.domains.source import load_index, split_entries
from omnilidar.domains.spec import effect_module
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec

RANGE_BINS = np.linspace(0.0, 80.0, 41)  # 2 m
INTENSITY_BINS = np.linspace(0.0, 1.0, 21)
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)

# Anchors' behaviour on real KITTI scans (REFERENCE.md section 4) and what ours does instead.
ANCHORS: dict[str, dict] = {
    "fog": {
        "anchor": "LiDAR_fog_sim / Robo3D",
        "weather_fraction": {"light": [0.0, 0.07], "moderate": [0.02, 0.16], "heavy": [0.12, 0.32]},
        "seconds_per_scan": 0.6,
        "difference": "Intensities stay in 0..1 (anchor: up to ~10); fog returns lie in the soft echo's "
                      "half-power interval in front of the target (anchor: jitter R0/U(R0-10, R0+10) throws "
                      "points behind the sensor or km away); attenuated returns under the detection floor "
                      "are lost (anchor: never).",
    },
    "wet_ground": {
        "anchor": "Bijelic model in LiDAR_snow_sim / Robo3D",
        "ground_lost_fraction": {"fed_0_255": [0.03, 0.08], "fed_0_1": [0.37, 0.84]},
        "seconds_per_scan": [0.05, 0.08],
        "difference": "Detection floor from the scan's own ground-intensity envelope (scale-free; the "
                      "anchor's histogram constants assume 0..255); cos(theta) instead of theta; only "
                      "points the water dims can be lost; ground from a platform-agnostic estimator.",
    },
    "snow": {
        "anchor": "LiDAR_snow_sim (Hahner 2022)",
        "clean_scan_deleted_by_noise_floor": [0.02, 0.13],
        "seconds_per_scan": [35.0, 42.0],
        "difference": "No global noise floor: beams no flake touches are returned bit for bit, so losses "
                      "grow with severity (anchor: 'light' can remove more than 'heavy'); flakes sampled per "
                      "beam in 3D with area occlusion; closed-form waveform peak.",
    },
    "rain": {
        "anchor": "LISA (Kilic 2021) / TripleMixer",
        "zero_remission_points_lost": 1.0,
        "seconds_per_scan": [7.0, 9.0],
        "difference": "Zero-remission points count as dim, not absent (LISA loses them all); detection "
                      "floor at the sensor's max range; only rain's attenuation or a stronger drop removes "
                      "a point; Poisson restriction to the drops that can win.",
    },
    "beam_reduction": {
        "anchor": "Beam-32 from elevation-based rings",
        "kept_fraction": 0.5,
        "difference": "Rings from per-scan calibrated elevation lines (laser offsets), not nominal angles.",
    },
    "beam_missing": {
        "anchor": "Robo3D beam missing",
        "beams_dropped": {"light": 16, "moderate": 32, "heavy": 48},
        "difference": "Same fractions (25/50/75 %); rings from calibrated recovery instead of azimuth-wrap "
                      "counting in file order.",
    },
}


def read_scans(paths: list[str | Path]) -> list[tuple[str, Scan]]:
    """Read KITTI-format scans; InputError if none are given."""
    if not paths:
        raise InputError(None, "no scans given (list KITTI .bin files in domains.fidelity.scans or pass "
                               "a SemanticKITTI index)")
    return [(str(p), semantickitti.read_scan(p)) for p in paths]


def index_scan_paths(index_path: str | Path, split: str, count: int) -> tuple[list[str], dict]:
    """The first ``count`` scans of one split of a SemanticKITTI index (in the embedded default the
    synthetic world's full HDL-64E sweeps) and where they come from (a ``data_source`` record)."""
    index = load_index(index_path, "semantickitti")
    entries = split_entries(index, split, index_path)
    if not entries:
        raise InputError(index_path, f"split {split!r} holds no scans")
    source = {index.get("dataset", "index"): record(str(index.get("root")), index.get("source") == "synthetic")}
    return [entry["points"] for entry in entries[:count]], source


def measure(scan: Scan, effect: str, severity: str, sensor: SensorSpec, seed: int) -> dict:
    """One application of an effect to a scan: fractions, weather-return values,
    intensity shifts and timings (raw arrays included for aggregation)."""
    module = effect_module(effect)
    rng = np.random.default_rng(seed)
    params = module.draw_params(severity, rng)
    ground, ground_s = None, 0.0
    if module.NEEDS_GROUND:
        t0 = time.perf_counter()
        ground = ground_estimation.estimate_ground(scan, sensor)
        ground_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out, info = module.apply(scan, params, sensor, rng, ground=ground, return_info=True)
    apply_s = time.perf_counter() - t0

    n = max(len(scan), 1)
    lost, changed, weather = info["lost"], info["changed"], info["weather"]
    kept_idx = np.flatnonzero(~lost)
    weather_in = np.zeros(len(scan), bool)
    weather_in[kept_idx[weather]] = True
    scale = float(scan.intensity_scale)
    added = out.points[weather]
    added_range = np.linalg.norm(added[:, :3].astype(np.float64), axis=1)
    added_int = added[:, 3].astype(np.float64) / scale
    plain = ~weather  # kept points that are still the target's return
    shift = (out.points[plain, 3].astype(np.float64) - scan.points[kept_idx[plain], 3].astype(np.float64)) / scale
    zero = scan.points[:, 3] == 0
    row = {
        "params": {k: (v.item() if isinstance(v, np.generic) else v) for k, v in params.items()},
        "changed": float(np.count_nonzero(changed & ~weather_in) / n),
        "lost": float(np.count_nonzero(lost) / n),
        "added": float(np.count_nonzero(weather) / n),
        "zero_remission_lost": float(np.count_nonzero(lost & zero) / max(np.count_nonzero(zero), 1)),
        "apply_s": apply_s,
        "ground_s": ground_s,
        "_added_range": added_range,
        "_added_intensity": added_int,
        "_shift": shift,
    }
    if ground is not None:
        row["ground_fraction"] = float(ground.mean())
        row["ground_lost"] = float(np.count_nonzero(lost & ground) / max(np.count_nonzero(ground), 1))
    return row


def _quantiles(values: np.ndarray) -> dict | None:
    if len(values) == 0:
        return None
    return {f"q{int(q * 100):02d}": float(np.quantile(values, q)) for q in QUANTILES}


def _spread(rows: list[dict], key: str) -> dict:
    vals = np.array([r[key] for r in rows], np.float64)
    return {"mean": float(vals.mean()), "min": float(vals.min()), "max": float(vals.max())}


def summarise(rows: list[dict]) -> dict:
    """Aggregate the measurements of one effect and severity over scans and seeds."""
    ranges = np.concatenate([r["_added_range"] for r in rows])
    ints = np.concatenate([r["_added_intensity"] for r in rows])
    shift = np.concatenate([r["_shift"] for r in rows])
    moved = shift[shift != 0]
    out = {key: _spread(rows, key) for key in ("changed", "lost", "added", "zero_remission_lost")}
    for key in ("ground_fraction", "ground_lost"):
        if key in rows[0]:
            out[key] = _spread(rows, key)
    out.update({
        "added_range_hist": np.histogram(np.clip(ranges, RANGE_BINS[0], RANGE_BINS[-1]), RANGE_BINS)[0].tolist(),
        "added_range_quantiles": _quantiles(ranges),
        "added_intensity_hist": np.histogram(np.clip(ints, 0.0, 1.0), INTENSITY_BINS)[0].tolist(),
        "added_intensity_quantiles": _quantiles(ints),
        "intensity_shift_mean": float(shift.mean()) if len(shift) else 0.0,
        "intensity_shift_mean_changed": float(moved.mean()) if len(moved) else 0.0,
        "intensity_shift_quantiles_changed": _quantiles(moved),
        "seconds_per_scan": float(np.median([r["apply_s"] + r["ground_s"] for r in rows])),
        "apply_seconds_median": float(np.median([r["apply_s"] for r in rows])),
        "ground_seconds_median": float(np.median([r["ground_s"] for r in rows])),
        "runs": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows],
    })
    return out


def fidelity_report(scans: list[tuple[str, Scan]], sensor: SensorSpec, effects: list[str], seeds: list[int],
                    progress: bool = True) -> dict:
    """{effect: {"severities": {severity: summary}, "anchor": {...}}} over all scans and seeds."""
    import sys

    from tqdm import tqdm

    report = {}
    jobs = [(e, s) for e in effects for s in effect_module(e).SEVERITIES]
    for effect, severity in tqdm(jobs, desc="fidelity", file=sys.stderr, disable=not progress):
        rows = [measure(scan, effect, severity, sensor, seed) for _, scan in scans for seed in seeds]
        entry = report.setdefault(effect, {"severities": {}, "anchor": ANCHORS.get(effect, {})})
        entry["severities"][severity] = summarise(rows)
    return report


def plot_report(report: dict, path: str | Path) -> None:
    """Four panels: fractions per effect and severity (with the anchors' fog range),
    range and intensity histograms of weather returns, and time per scan vs anchors."""
    from omnilidar.io.figure import plt, save_figure

    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    ax = axes[0, 0]
    labels, x = [], 0
    for effect, entry in report.items():
        for severity, s in entry["severities"].items():
            for k, (key, colour) in enumerate((("changed", "C0"), ("lost", "C3"), ("added", "C2"))):
                v = s[key]
                ax.bar(x + (k - 1) * 0.27, v["mean"], 0.27, color=colour,
                       yerr=[[max(v["mean"] - v["min"], 0.0)], [max(v["max"] - v["mean"], 0.0)]], capsize=2,
                       label=key if x == 0 else None)
            anchor = entry["anchor"].get("weather_fraction", {}).get(severity)
            if anchor:
                ax.plot([x + 0.27 - 0.14, x + 0.27 + 0.14], [anchor[0]] * 2, "k-", lw=1)
                ax.plot([x + 0.27 - 0.14, x + 0.27 + 0.14], [anchor[1]] * 2, "k-", lw=1,
                        label="anchor fog range" if "anchor fog range" not in ax.get_legend_handles_labels()[1] else None)
            labels.append(f"{effect}\n{severity}")
            x += 1
    ax.set_xticks(range(len(labels)), labels, fontsize=6, rotation=90)
    ax.set_ylabel("fraction of points (min-max over scans x seeds)")
    ax.set_title("points changed / lost / turned into weather returns")
    ax.legend(fontsize=7)

    centres_r = 0.5 * (RANGE_BINS[1:] + RANGE_BINS[:-1])
    centres_i = 0.5 * (INTENSITY_BINS[1:] + INTENSITY_BINS[:-1])
    for effect, entry in report.items():
        for severity, s in entry["severities"].items():
            if sum(s["added_range_hist"]) == 0:
                continue
            h = np.asarray(s["added_range_hist"], float)
            axes[0, 1].step(centres_r, h / h.sum(), where="mid", label=f"{effect} {severity}")
            h = np.asarray(s["added_intensity_hist"], float)
            axes[1, 0].step(centres_i, h / h.sum(), where="mid", label=f"{effect} {severity}")
    axes[0, 1].set(xlabel="range of weather returns (m)", ylabel="share", title="weather returns: range")
    axes[1, 0].set(xlabel="intensity of weather returns (0..1)", ylabel="share", title="weather returns: intensity")
    for a in (axes[0, 1], axes[1, 0]):
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=6)

    ax = axes[1, 1]
    names = list(report)
    ours = [max(s["seconds_per_scan"] for s in report[e]["severities"].values()) for e in names]
    ax.bar(range(len(names)), ours, 0.4, label="ours (slowest severity, median)")
    for i, e in enumerate(names):
        t = report[e]["anchor"].get("seconds_per_scan")
        if t is not None:
            lo, hi = (t, t) if np.isscalar(t) else t
            ax.plot([i + 0.3, i + 0.3], [lo, hi], "k_-", ms=10, label="anchor" if i == 0 or "anchor" not in
                    ax.get_legend_handles_labels()[1] else None)
    ax.set_yscale("log")
    ax.set_xticks(range(len(names)), names, fontsize=7)
    ax.set(ylabel="seconds per scan (1 core)", title="time per scan vs anchors")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
