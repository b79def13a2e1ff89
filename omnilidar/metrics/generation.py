"""All generation-quality metrics of a generated set against a real set.

Both sets are (N, 2, H, W) range images in the R2DM encoding, decoded with the
generator's geometry (``views.range_views``), so real and generated scans go
through exactly the same preprocessing (the protocol's 0.5-63 m mask). From a
set ``set_features`` computes, in batches,

* the BEV histograms of the masked pixels' points (R2Flow protocol, ``bev.py``);
* the features of every requested extractor (FRD, FRID, FSVD, FPVD, FPD).

``compare`` turns two such feature sets into the scores: JSD, MMD (raw and
x1e-4), and the squared Frechet distance of each feature metric, each with the
weights tag that produced it. Real-set features are computed once and reused
for every generated set (samplers, presets, baselines).

Frechet distances need at least 2 scans per set; with fewer scans than feature
dimensions the covariances are singular and the exact Gram route of
``frechet_from_features`` is used (small sets give biased, noisy values: the
number of scans is recorded with every score).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from omnilidar.data.range_image import RangeImageSpec
from omnilidar.errors import InputError
from omnilidar.metrics.bev import bev_histograms, bev_scores_from_histograms
from omnilidar.metrics.extractors import METRIC_NAMES
from omnilidar.metrics.extractors.views import range_views
from omnilidar.metrics.frechet import frechet_from_features


@dataclass
class FeatureSet:
    """What the metrics need of one set of scans."""

    num_scans: int
    bev: np.ndarray  # (N, 100, 100) histograms
    features: dict[str, np.ndarray] = field(default_factory=dict)  # kind -> (N, D)
    seconds: dict[str, float] = field(default_factory=dict)  # kind -> extraction time


    def rows(self, index) -> "FeatureSet":
        """The scans ``index`` (a slice or index array) of this set; extraction times are not split."""
        return FeatureSet(len(self.bev[index]), self.bev[index], {k: v[index] for k, v in self.features.items()})


def set_features(images, spec: RangeImageSpec, extractors: dict, batch_size: int = 8, source=None) -> FeatureSet:
    """Protocol views, BEV histograms and features of a set of (N, 2, H, W) range images.

    ``extractors``: {kind: LoadedExtractor} (``weights.load_extractor``).
    """
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or len(images) == 0:
        raise InputError(source, f"expected a non-empty (N, 2, H, W) set of range images, got {images.shape}")
    hists, feats = [], {k: [] for k in extractors}
    seconds = {k: 0.0 for k in ["bev", *extractors]}
    for start in range(0, len(images), batch_size):
        views = range_views(images[start : start + batch_size], spec, source)
        t0 = time.perf_counter()
        hists.append(bev_histograms(views["points"]))
        seconds["bev"] += time.perf_counter() - t0
        for kind, ext in extractors.items():
            t0 = time.perf_counter()
            f = np.asarray(ext.extract(views), dtype=np.float64)
            seconds[kind] += time.perf_counter() - t0
            if not np.isfinite(f).all():
                raise RuntimeError(f"{METRIC_NAMES[kind]} extractor produced non-finite features")
            feats[kind].append(f)
    return FeatureSet(len(images), np.concatenate(hists), {k: np.concatenate(v) for k, v in feats.items()}, seconds)


def compare(real: FeatureSet, generated: FeatureSet, extractors: dict) -> dict:
    """Scores of ``generated`` against ``real``: {"JSD", "MMD", "MMD_1e4", <FEATURE>...,
    "weights": {metric: tag}, "comparable_with_paper": {metric: bool}, counts}.

    A set whose every scan is empty in the BEV band gets JSD/MMD ``None`` and a
    note instead of an error, so that one degenerate generator does not hide the
    others' numbers; nothing returned is NaN or Inf.
    """
    out: dict = {"n_real": real.num_scans, "n_generated": generated.num_scans, "weights": {},
                 "comparable_with_paper": {}, "notes": []}
    try:
        bev = bev_scores_from_histograms(real.bev, generated.bev)
        out.update(JSD=bev.jsd, MMD=bev.mmd, MMD_1e4=bev.mmd_1e4, empty_generated=bev.empty_generated)
    except InputError as err:
        out.update(JSD=None, MMD=None, MMD_1e4=None)
        out["notes"].append(f"BEV metrics undefined: {err}")
    for kind, ext in extractors.items():
        name = METRIC_NAMES[kind]
        a, b = real.features.get(kind), generated.features.get(kind)
        if a is None or b is None:
            continue
        if len(a) < 2 or len(b) < 2:
            out[name] = None
            out["notes"].append(f"{name} needs at least 2 scans per set")
        else:
            out[name] = float(frechet_from_features(a, b))
        out["weights"][name] = ext.weights
        out["comparable_with_paper"][name] = bool(ext.comparable_with_paper)
    return out


def generation_metrics(real_images, generated_images, spec: RangeImageSpec, extractors: dict,
                       batch_size: int = 8) -> dict:
    """One-shot convenience: ``compare`` of the two sets' ``set_features``."""
    real = set_features(real_images, spec, extractors, batch_size, "real set")
    gen = set_features(generated_images, spec, extractors, batch_size, "generated set")
    return compare(real, gen, extractors)


# --------------------------------------------------------------------------- scan sets


def real_domain_images(domains_index, domain: str, shape: tuple[int, int], limit: int) -> np.ndarray:
    """Up to ``limit`` real range images of one built domain, (N, 2, H, W), in file order
    (the protocol's real set; ``bev.protocol_subset`` shuffles large ones)."""
    from omnilidar.generator.data import load_range_image, read_domains_index

    domains = read_domains_index(domains_index)
    if domain not in domains:
        raise InputError(domains_index, f"no domain {domain!r} (built: {', '.join(domains)})")
    files = domains[domain]["files"][: max(1, int(limit))]
    return np.stack([load_range_image(f, shape) for f in files])


# Training scans per domain that calibration candidates are compared with (the first ones).
REFERENCE_SCANS = 64


def closest_setting(candidates: dict[str, np.ndarray], reference: np.ndarray, spec: RangeImageSpec) -> tuple[str, dict]:
    """The label of the candidate scan set (each (N, 2, H, W)) closest to ``reference``'s scans, and
    every candidate's BEV JSD and MMD against them: the lowest sum of each metric relative to its
    best, so that both count alike."""
    real = set_features(reference, spec, {}, 8, "reference")
    scores = {label: {m: compare(real, set_features(images, spec, {}, 8, label), {})[m] for m in ("JSD", "MMD")}
              for label, images in candidates.items()}
    best = {m: min(s[m] for s in scores.values()) for m in ("JSD", "MMD")}
    pick = min(scores, key=lambda label: sum(scores[label][m] / max(best[m], 1e-12) for m in best))
    return pick, scores


def group_scores(real: FeatureSet, generated: FeatureSet, extractors: dict, groups: int, metrics: list[str]) -> dict:
    """Each metric's mean and std over ``groups`` disjoint groups of the generated scans (their
    sampling seeds differ), each scored against the whole real set."""
    size = generated.num_scans // groups
    runs = [compare(real, generated.rows(slice(g * size, (g + 1) * size)), extractors) for g in range(groups)]
    out = {"weights": runs[0]["weights"], "comparable_with_paper": runs[0]["comparable_with_paper"],
           "scans_per_group": size}
    for m in metrics:
        vals = [r.get("MMD_1e4" if m == "MMD" else m) for r in runs]
        ok = all(v is not None for v in vals)
        out[m] = float(np.mean(vals)) if ok else None
        out[f"{m}_std"] = float(np.std(vals, ddof=1)) if ok and groups > 1 else None
        out[f"{m}_groups"] = vals
    return out


def excess_in_spreads(mine: dict, theirs: dict, m: str) -> float:
    """How far ``mine`` lies over ``theirs`` on metric ``m`` (each :func:`group_scores`), in units of
    two standard deviations of the difference (the two spreads combined; negative: better): at
    most 1 holds, the student check's rule."""
    import math

    return (mine[m] - theirs[m]) / max(2 * math.hypot(mine[f"{m}_std"], theirs[f"{m}_std"]), 1e-12)


def first_holding_setting(candidates: dict[str, np.ndarray], reference: np.ndarray, spec: RangeImageSpec,
                          groups: int = 4) -> tuple[str, dict]:
    """The first candidate scan set (in the order given) that holds the best candidate of every
    metric (BEV JSD and MMD against ``reference``'s scans) by the student check's rule, each set
    scored in ``groups`` disjoint groups: a setting that itself misses the bar is not a target to
    calibrate on. Where none holds, the closest (:func:`closest_setting`). Scores: each candidate's
    JSD, MMD (means) and ``excess`` (the worst metric's, :func:`excess_in_spreads`)."""
    real = set_features(reference, spec, {}, 8, "reference")
    groups = max(2, min(groups, min(len(images) for images in candidates.values())))
    stats = {label: group_scores(real, set_features(images, spec, {}, 8, label), {}, groups, ["JSD", "MMD"])
             for label, images in candidates.items()}
    best = {m: min(stats, key=lambda label: stats[label][m]) for m in ("JSD", "MMD")}
    scores = {label: {"JSD": s["JSD"], "MMD": s["MMD"] * 1e-4,
                      "excess": max(excess_in_spreads(s, stats[best[m]], m) for m in best)}
              for label, s in stats.items()}
    holding = [label for label in candidates if scores[label]["excess"] <= 1.0]
    return (holding[0] if holding else closest_setting(candidates, reference, spec)[0]), scores


CALIBRATION_RULES = {"closest": closest_setting, "first_holding": first_holding_setting}


def choose_on_training_scans(domains_index, spec: RangeImageSpec, rule: str = "closest"):
    """A distillation's calibration rule (``choose`` of
    :func:`omnilidar.generator.return_decision.calibrate_returns`) against the domain's first
    training scans: ``closest`` (:func:`closest_setting`) or ``first_holding``
    (:func:`first_holding_setting`)."""
    from omnilidar.generator.data import load_range_image, read_domains_index

    domains, pick = read_domains_index(domains_index), CALIBRATION_RULES[rule]

    def choose(domain: str, candidates: dict[str, np.ndarray]) -> tuple[str, dict]:
        files = domains[domain]["files"][:REFERENCE_SCANS]
        return pick(candidates, np.stack([load_range_image(f, spec.shape) for f in files]), spec)

    return choose


def domain_sources(domains_index, domains: list[str]) -> dict[str, str | None]:
    """Where each domain's built scans come from, "<dataset> <split>" (the shards' sidecars; several
    splits joined by "+"), or None where a shard has no sidecar that says."""
    import json

    from omnilidar.generator.data import read_domains_index

    index = read_domains_index(domains_index)
    out = {}
    for domain in domains:
        if domain not in index:
            raise InputError(domains_index, f"no domain {domain!r} (built: {', '.join(index)})")
        found = set()
        for shard_dir in index[domain]["shard_dirs"]:
            sidecar = shard_dir / "sidecar.json"
            side = json.loads(sidecar.read_text()) if sidecar.is_file() else {}
            found.add(f"{side['dataset']} {side['split']}" if "dataset" in side and "split" in side else None)
        out[domain] = None if None in found else "+".join(sorted(found))
    return out


def dataset_images(index_path, split: str, spec: RangeImageSpec, limit: int) -> np.ndarray:
    """Up to ``limit`` scans of a dataset split (index JSON), projected to range images."""
    from omnilidar.data.index import read_index

    entries = read_index(index_path)["splits"].get(split) or []
    if not entries:
        raise InputError(index_path, f"split {split!r} has no scans")
    return entry_images(entries[: max(1, int(limit))], spec)


def entry_images(entries: list[dict], spec: RangeImageSpec) -> np.ndarray:
    """The scans of index or subset entries ({"points": .bin path}), projected to range images."""
    from omnilidar.data.range_image import encode, project
    from omnilidar.io.semantickitti import read_points

    out = []
    for entry in entries:
        proj = project(read_points(entry["points"]), spec)
        out.append(encode(proj.range_img, proj.intensity_img, spec))
    return np.stack(out)


def sample_images(denoiser, payload: dict, prompt_cache: dict, domain: str, count: int, sampler: str, steps: int,
                  seed: int, batch_size: int = 8, autocast_bf16: bool = False) -> tuple[np.ndarray, float]:
    """``count`` generated range images of ``domain`` (per-scan seeds as in ``omnilidar sample``)
    and the wall-clock seconds per scan (the images come back on the CPU, so a GPU has finished)."""
    import torch

    from omnilidar.generator.diffusion import generate, scan_seed
    from omnilidar.generator.schedule import CosineLogSNRSchedule
    from omnilidar.generator.unet import range_image_spec

    settings = payload["config"]
    if domain not in payload["domains"]:
        raise InputError(None, f"the generator does not know domain {domain!r}")
    entry = prompt_cache["domains"][domain]
    d = settings["diffusion"]
    schedule = CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"])
    spec = range_image_spec(settings)
    out = []
    t0 = time.perf_counter()
    for start in range(0, count, batch_size):
        seeds = [scan_seed(seed, domain, g) for g in range(start, min(count, start + batch_size))]
        with torch.no_grad():
            out.append(generate(denoiser, payload["domains"].index(domain), entry["tokens"][0], entry["mask"][0],
                                seeds, spec.shape, sampler, steps, schedule, autocast_bf16=autocast_bf16).numpy())
    seconds = (time.perf_counter() - t0) / max(1, count)
    return np.concatenate(out), seconds


# --------------------------------------------------------------------------- domain statistics

RANGE_PROFILE_EDGES = np.arange(0.0, 85.0, 5.0)


def domain_statistics(images, spec: RangeImageSpec, near_range: float = 5.0) -> dict:
    """Statistics that tell the domains apart, averaged over a set of range images:
    empty-row fraction (Beam-32), near-range point fraction (fog/snow/rain clutter),
    points per scan, mean elevation and range of the returns, and the elevation
    (valid fraction per row) and range (5 m bins) profiles (drone, quadruped)."""
    from omnilidar.data.range_image import decode, pixel_angles

    img = np.asarray(images, dtype=np.float32)
    elev = np.degrees(pixel_angles(spec)[0])
    valid = np.empty((len(img), *spec.shape), bool)
    depth = np.zeros((len(img), *spec.shape), np.float64)
    for b, one in enumerate(img):
        d, _, v = decode(one, spec)
        valid[b], depth[b] = v, np.where(v, d, 0.0)
    n = valid.reshape(len(img), -1).sum(1)
    total = max(int(n.sum()), 1)
    rows = valid.any(axis=2)
    hist = np.histogram(depth[valid], bins=RANGE_PROFILE_EDGES)[0]
    return {
        "scans": len(img),
        "empty_row_fraction": float(1.0 - rows.mean()),
        "near_range_fraction": float(((depth < near_range) & valid).sum() / total),
        "points_per_scan": float(n.mean()),
        "mean_elevation_deg": float((valid * elev[None, :, None]).sum() / total),
        "mean_range_m": float(depth[valid].mean()) if valid.any() else 0.0,
        "elevation_profile": valid.mean(axis=(0, 2)).round(4).tolist(),
        "range_profile": (hist / max(hist.sum(), 1)).round(4).tolist(),
    }


def across_domain_correlation(real: dict[str, dict], generated: dict[str, dict], keys) -> dict[str, float | None]:
    """Domain control in one number per statistic: the Pearson correlation, across domains,
    between the real and the generated value of each statistic (``real[domain][key]``).
    None where either side does not vary across the domains (no signal to follow)."""
    doms = [d for d in real if d in generated]
    out = {}
    for k in keys:
        a = np.array([real[d][k] for d in doms], np.float64)
        b = np.array([generated[d][k] for d in doms], np.float64)
        if len(doms) < 3 or a.std() < 1e-9 * max(1.0, np.abs(a).max()) or b.std() < 1e-9 * max(1.0, np.abs(b).max()):
            out[k] = None
        else:
            out[k] = float(np.corrcoef(a, b)[0, 1])
    return out
