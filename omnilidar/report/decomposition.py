"""The GDA decomposition study: taking the chain apart, row by row.

Every row trains the same backbone from scratch on the same label subset with
the same schedule and seeds; only what is added differs (N scans each):

    supervised_only   nothing
    real_truth        N further real train scans with their true labels (the ceiling at this budget)
    real_pseudo       the same N real scans labelled by the labeler (what pseudo-labelling costs)
    generated         N generated scans of the domain labelled by the labeler (the method)
    lasermix          the same N real scans LaserMix-ed with the labelled ones, labeler's labels
    simulated         (weather study) the N real scans through the domain's scene, labels carried
    round_trip_truth  the N real scans through the generator's range image and back, true labels
                      carried (a perfect generator at this image size)
    round_trip_pseudo the same round-tripped scans labelled by the labeler

Differences between rows are taken seed by seed (rows share their seeds), so
the spread of a difference is not the sum of two rows' spreads. What each link
costs:

    pseudo_labels     real_truth - real_pseudo   (the labeler's errors on real scans)
    samples           real_pseudo - generated    (generated instead of real scans, same labeler)
    vs_lasermix       lasermix - generated       (the semi-supervised alternative on the same labeler)
    vs_simulation     simulated - generated      (physical simulation against the generator's scans)

and, with the round-trip rows, the chain from the ceiling to GDA one link at a time:

    resolution        real_truth - round_trip_truth         (what the image size loses)
    labels            round_trip_truth - round_trip_pseudo  (the labeler, on scans of that size)
    generator         round_trip_pseudo - generated         (the generator against a perfect one)
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from omnilidar.downstream.seg.experiments import runs_by_seed, seed_statistics
from omnilidar.errors import InputError
from omnilidar.report.compute_trend import FAR_DECADES, fit_line

ROWS = ("supervised_only", "real_truth", "real_pseudo", "generated", "lasermix")
HELDOUT = "heldout"  # train-split scans outside the subset and the pool: where the regime is checked
SIMULATED = "simulated"  # the weather study's extra row: the pool through the domain builder, labels carried
ROUND_TRIP = ("round_trip_truth", "round_trip_pseudo")  # the pool through the generator's image and back
OPTIONAL_ROWS = (SIMULATED, *ROUND_TRIP)  # present when their runs are given
ROLE_OF_ROW = {"supervised_only": "supervised_only", "real_truth": "real_truth", "real_pseudo": "real_pseudo",
               "generated": "gda", "lasermix": "lasermix", SIMULATED: "simulated",
               "round_trip_truth": "round_trip_truth", "round_trip_pseudo": "round_trip_pseudo"}
ROW_LABELS = {"supervised_only": "supervised only", "real_truth": "+N real, true labels",
              "real_pseudo": "+N real, labeler's labels", "generated": "+N generated (GDA)",
              "lasermix": "+N real, LaserMix", SIMULATED: "+N real, simulated domain",
              "round_trip_truth": "+N real via range image, true", "round_trip_pseudo": "+N real via range image, labeler"}
LINKS = {"pseudo_labels": ("real_truth", "real_pseudo"), "samples": ("real_pseudo", "generated"),
         "vs_lasermix": ("lasermix", "generated"), "vs_simulation": (SIMULATED, "generated"),
         "resolution": ("real_truth", "round_trip_truth"), "labels": ("round_trip_truth", "round_trip_pseudo"),
         "generator": ("round_trip_pseudo", "generated")}
CHAIN = ("resolution", "labels", "generator")  # ceiling -> GDA, one link at a time (round-trip rows)


def study_rows(roles) -> tuple[str, ...]:
    """The rows a study has: the five, plus the simulated and round-trip rows when their runs are given."""
    return ROWS + tuple(row for row in OPTIONAL_ROWS if ROLE_OF_ROW[row] in roles)


def pooled_set(doc: dict, prefix: str) -> dict:
    """Scores of the sets named ``prefix/<severity>`` of an evaluation, averaged (mIoU, per-class IoU)."""
    sets = [v for k, v in doc["sets"].items() if k.startswith(prefix + "/")]
    if not sets:
        raise InputError(doc["_path"], f"holds no {prefix}/<severity> sets")
    classes = sets[0]["iou"]
    return {"miou": float(np.mean([s["miou"] for s in sets])),
            "iou": {c: float(np.mean([s["iou"][c] for s in sets])) for c in classes},
            "sets": sorted(k for k in doc["sets"] if k.startswith(prefix + "/"))}


def paired_difference(a: list[float], b: list[float]) -> dict:
    """Mean and sample standard deviation of the per-seed differences a - b."""
    diff = np.asarray(a) - np.asarray(b)
    return {"per_seed": diff.tolist(), "mean": float(diff.mean()),
            "std": float(diff.std(ddof=1)) if len(diff) > 1 else None}


def backbone_study(roles: dict[str, list[dict]], backbone: str, evalset: str = "val") -> dict:
    """Rows, gaps to supervised-only and link costs of one backbone's runs (role -> docs by seed),
    scored on ``evalset``."""
    names = study_rows(roles)
    missing = [row for row in names if ROLE_OF_ROW[row] not in roles]
    if missing:
        raise InputError(None, f"{backbone}: no evaluation of row(s) {', '.join(missing)}")
    rows, seeds = {}, None
    for row in names:
        docs = roles[ROLE_OF_ROW[row]]
        stats = seed_statistics(docs, evalset)
        if seeds is None:
            seeds = stats["seeds"]
        elif stats["seeds"] != seeds:
            raise InputError(docs[0]["_path"], f"{backbone} {row}: seeds {stats['seeds']} differ from {seeds}")
        train = docs[0]["train"]
        rows[row] = {**stats, "added_scans": train["num_generated"], "real_scans": train["num_real"],
                     "iterations": train["iterations"], "train_seconds": [d["train"]["seconds"] for d in docs],
                     "checkpoints": [d["checkpoint"] for d in docs]}
    base = rows["supervised_only"]["miou"]
    for row in names[1:]:
        rows[row]["gain_over_supervised"] = paired_difference(rows[row]["miou"], base)
    ceiling = rows["real_truth"]["gain_over_supervised"]["mean"]
    generated = rows["generated"]["gain_over_supervised"]["mean"]
    check = regime_check(roles)
    return {
        "seeds": seeds, "rows": rows,
        "evalset": evalset,
        "links": {name: paired_difference(rows[a]["miou"], rows[b]["miou"]) for name, (a, b) in LINKS.items()
                  if a in rows and b in rows},
        "regime_check": check,
        "ceiling_clears_two_std": check["ceiling_clears_two_std"],
        # The same test on the scored set, reported only: the regime is chosen on the held-out scans.
        "ceiling_on_evalset": ceiling_test(rows["supervised_only"], rows["real_truth"]),
        # Where the method lands between supervised-only (0) and the ceiling (1).
        "generated_share_of_ceiling": generated / ceiling if ceiling > 0 else None,
    }


def regime_check(roles: dict[str, list[dict]]) -> dict:
    """Can this regime answer the question? On the held-out train scans (never val), the ceiling
    (+N real scans, true labels) must clear supervised-only by two standard deviations."""
    docs = {row: roles[ROLE_OF_ROW[row]] for row in ("supervised_only", "real_truth")}
    if not all(HELDOUT in d["sets"] for ds in docs.values() for d in ds):
        return {"set": None, "ceiling_clears_two_std": None,
                "note": "no held-out scores in these evaluations; the regime is checked by the main study"}
    stats = {row: seed_statistics(ds, HELDOUT) for row, ds in docs.items()}
    return {"set": HELDOUT, "supervised_only": stats["supervised_only"], "real_truth": stats["real_truth"],
            **ceiling_test(stats["supervised_only"], stats["real_truth"])}


def ceiling_test(supervised: dict, ceiling: dict) -> dict:
    """Does the ceiling clear supervised-only by two standard deviations (the larger row's, over
    seeds)? The gain is taken seed by seed; one seed never clears."""
    gain = paired_difference(ceiling["miou"], supervised["miou"])
    spread = max(supervised["miou_std"] or 0.0, ceiling["miou_std"] or 0.0)
    return {"ceiling_gain": gain, "two_std": 2 * spread,
            "ceiling_clears_two_std": bool(len(gain["per_seed"]) > 1 and gain["mean"] > 2 * spread)}


def costliest_link(study: dict) -> str | None:
    """The link that loses the most mIoU, or None when none loses: along the chain (resolution,
    labels, generator) when the round-trip rows were run, else pseudo_labels or samples."""
    chain = CHAIN if all(k in study["links"] for k in CHAIN) else ("pseudo_labels", "samples")
    costs = {k: study["links"][k]["mean"] for k in chain}
    name = max(costs, key=costs.get)
    return name if costs[name] > 0 else None


def attempt_record(study: dict, docs: list[dict], name: str, backbone: str) -> dict:
    """One remedy tried on the generated row: its seeds' scores and its gains, seed by seed, over
    the plain generated row and over supervised-only."""
    stats = seed_statistics(docs, study["evalset"])
    if stats["seeds"] != study["seeds"]:
        raise InputError(docs[0]["_path"], f"{backbone} attempt {name}: seeds {stats['seeds']} differ from "
                                           f"{study['seeds']}")
    return {**stats, "mixing": docs[0]["train"].get("mixing"), "iterations": docs[0]["train"]["iterations"],
            "gain_over_generated": paired_difference(stats["miou"], study["rows"]["generated"]["miou"]),
            "gain_over_supervised": paired_difference(stats["miou"], study["rows"]["supervised_only"]["miou"])}


def decomposition(evaluations: list[dict], attempts: dict[str, list[dict]] | None = None,
                  evalset: str = "val") -> dict:
    """backbone -> study, from the evaluate-segmentor outputs of every row, backbone and seed, and
    of every attempt (name -> its runs' outputs). ``evalset`` other than val: the sets
    ``evalset/<severity>`` of each evaluation, averaged (a corruption at every severity)."""
    if evalset != "val":
        for doc in evaluations + [d for docs in (attempts or {}).values() for d in docs]:
            doc["sets"][evalset] = pooled_set(doc, evalset)
    out = {}
    for backbone, roles in sorted(runs_by_seed(evaluations).items()):
        study = backbone_study(roles, backbone, evalset)
        tried = {}
        for name, docs in (attempts or {}).items():
            mine = sorted((d for d in docs if d["model"]["backbone"] == backbone), key=lambda d: d["seed"])
            if not mine:
                raise InputError(None, f"attempt {name}: no {backbone} run given")
            tried[name] = attempt_record(study, mine, name, backbone)
        out[backbone] = study | {"costliest_link": costliest_link(study), "attempts": tried}
    return out


def _edit_point(override: dict, main_iterations: int | None) -> tuple[int | None, str, str, float] | None:
    """(generator iterations, recipe, labels, sampling strength) of an attempt that changes only its
    generator and at most the sampling strength there, else None: the attempts that make a point
    of a strength curve. ``recipe`` names the generator keys it changes besides the iterations
    ("" for the main generator's recipe); ``labels`` is the labeler's, ``carried`` from each
    edit's source scan, or "labeler (<key value, ...>)" for an attempt's own labeler."""
    gen = override.get("generator")
    if set(override) - {"labels", "labeler"} != {"generator"} or not gen or set(gen.get("sampling", {})) - {"strength"}:
        return None
    changed = _flat({k: v for k, v in gen.items() if k != "sampling"})
    changed.pop("training.iterations", None)
    labels = override.get("labels", "labeler")
    if override.get("labeler"):
        labels = f"labeler ({_words(_flat(override['labeler']))})"
    return (gen.get("training", {}).get("iterations", main_iterations), _words(changed), labels,
            float(gen.get("sampling", {}).get("strength", 1.0)))


def _words(flat: dict) -> str:
    """ "key value, ..." of flattened settings, sorted."""
    return ", ".join(f"{k} {v}" for k, v in sorted(flat.items()))


def _flat(tree: dict, prefix: str = "") -> dict:
    """{"a.b": value} for every leaf of a nested dict."""
    out = {}
    for k, v in tree.items():
        out |= _flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v}
    return out


def log_crossing(xs: list[float], gains: list[float]) -> float | None:
    """Where the mean gain first falls below 0 going up ``xs`` (> 0, spanning decades: sampling
    strengths, range noise), interpolated linearly in log x between the two points around it;
    None when it never does or is below 0 from the start."""
    for (s0, g0), (s1, g1) in zip(zip(xs, gains), zip(xs[1:], gains[1:])):
        if g0 >= 0 > g1:
            return float(10 ** (np.log10(s0) + (np.log10(s1) - np.log10(s0)) * g0 / (g0 - g1)))
    return None


NOISE_SAMPLING_KEYS = {"strength", "keep_source", "range_noise"}


def range_noise_curve(study: dict, attempts: dict) -> dict | None:
    """Gain over supervised-only against a known range error: attempts that keep real scans (a
    strength below 0.01, remission kept or edited alike), carry their true labels and add
    ``sampling.range_noise`` to every return's encoded log-range. The carried attempt at the same
    strength without noise is the curve's zero. ``crossing_noise``: how much per-point range noise
    scans can carry before they stop paying, the precision a generator's ranges must reach."""
    points, zero = {}, None
    for name, override in attempts.items():
        gen = override.get("generator", {})
        sampling = gen.get("sampling", {})
        if (override.get("labels") != "carried" or set(override) != {"labels", "generator"} or set(gen) != {"sampling"}
                or set(sampling) - NOISE_SAMPLING_KEYS or sampling.get("strength", 1.0) >= 0.01
                or name not in study["attempts"]):
            continue
        noise = float(sampling.get("range_noise", 0.0))
        if noise > 0:
            points[noise] = name
        elif not sampling.get("keep_source"):
            zero = name
    if not points:
        return None
    order = sorted(points)
    gains = [study["attempts"][points[n]]["gain_over_supervised"] for n in order]
    return {"noise_std": order, "rows": [points[n] for n in order], "gain_mean": [g["mean"] for g in gains],
            "gain_std": [g["std"] for g in gains], "gain_per_seed": [g["per_seed"] for g in gains],
            "zero": None if zero is None else {"row": zero, **study["attempts"][zero]["gain_over_supervised"]},
            "crossing_noise": log_crossing(order, [g["mean"] for g in gains]),
            "units": "std of the encoded log-range, 2 log2(range + 1) / log2(max_range + 1) - 1"}


def strength_curves(study: dict, attempts: dict, main_iterations: int | None) -> dict:
    """Gain over supervised-only against the sampling strength, one curve per generator budget.

    An SDEdit attempt (``generator.sampling.strength`` < 1, nothing else changed but the generator's
    iterations) starts each generated scan from one of the generator's training scans noised to
    t = strength; the plain generated row (and an attempt with only other iterations) is strength 1.
    A tiny strength (e.g. 0.001) gives the training scans themselves, labelled: what the generator's
    data is worth. ``crossing_strength``: how much of a scan the generator can make before the scans
    stop paying. Attempts with ``labels: carried`` make curves of their own (keyed "<iterations>
    carried"): the same edits under their sources' true labels instead of the labeler's, which
    splits what the edits cost the labeler from what they cost the student; so do generators of
    another recipe (other generator keys, keyed "<iterations> (<key value, ...>)")."""
    points: dict[tuple, dict[float, tuple[str, dict]]] = {
        (main_iterations, "", "labeler"): {1.0: ("generated", study["rows"]["generated"])}}
    for name, override in attempts.items():
        where = _edit_point(override, main_iterations)
        if where is not None and name in study["attempts"]:
            points.setdefault(where[:3], {})[where[3]] = (name, study["attempts"][name])
    curves = {}
    for (iterations, recipe, labels), by_strength in sorted(points.items(),
                                                            key=lambda kv: (kv[0][0] or 0, kv[0][1], kv[0][2] != "labeler")):
        if not any(0 < st < 1 for st in by_strength):
            continue
        order = sorted(by_strength)
        gains = [by_strength[st][1]["gain_over_supervised"] for st in order]
        key = " ".join([str(iterations)] + [f"({recipe})"] * bool(recipe) + [labels] * (labels != "labeler"))
        curves[key] = {
            "iterations": iterations, "recipe": recipe, "labels": labels, "strength": order,
            "rows": [by_strength[st][0] for st in order],
            "gain_mean": [g["mean"] for g in gains], "gain_std": [g["std"] for g in gains],
            "gain_per_seed": [g["per_seed"] for g in gains],
            "crossing_strength": log_crossing(order, [g["mean"] for g in gains])}
    return curves


def curve_words(curve: dict) -> str:
    """What sets a strength curve apart from the main generator's under the labeler's labels."""
    labels = curve.get("labels", "labeler")
    return ("" if not curve.get("recipe") else f" ({curve['recipe']})") + (
        ", sources' true labels" if labels == "carried" else "" if labels == "labeler" else f", {labels}")


def strength_trend(curves: dict) -> dict:
    """Crossing strength against log10(generator iterations), least squares over the budgets
    that have one: at what budget the crossing would reach strength 1 (fresh samples paying).
    With two budgets it is the line through them: a direction, not a measured trend."""
    known = [(c["iterations"], c["crossing_strength"]) for c in curves.values()
             if c["iterations"] and c["crossing_strength"] is not None and c.get("labels", "labeler") == "labeler"
             and not c.get("recipe")]
    out = {"budgets": [k[0] for k in known], "crossing_strengths": [k[1] for k in known],
           "slope_per_decade": None, "iterations_at_strength_1": None}
    if len({k[0] for k in known}) < 2:
        return out | {"note": "fewer than two generator budgets with a crossing"}
    slope, intercept, error = fit_line(np.log10([k[0] for k in known]), np.asarray([k[1] for k in known]))
    out["slope_per_decade"], out["slope_std_error"] = slope, error
    if slope <= 0:
        return out | {"note": "the crossing does not move towards fresh samples with more compute"}
    how = "the line through two budgets" if len(known) == 2 else f"a fit over {len(known)} budgets"
    decades = (1.0 - intercept) / slope
    if decades > FAR_DECADES:  # a crossing that barely moves: no budget anyone could spend
        return out | {"note": f"{how}: at this rate strength 1 lies beyond 1e{FAR_DECADES} generator iterations"}
    return out | {"iterations_at_strength_1": float(10 ** decades), "note": how}


def decomposition_figure(path: str | Path, doc: dict) -> None:
    """One panel per backbone: each row's mean val mIoU with its standard deviation and every
    seed as a dot; a dashed line at supervised-only. Written atomically as PNG."""
    from omnilidar.io.figure import plt, save_figure

    studies = doc["backbones"]
    chained = all(all(k in st["links"] for k in CHAIN) for st in studies.values())
    curved = all(st.get("strength_curves") for st in studies.values())
    noisy = all(st.get("range_noise_curve") for st in studies.values())
    heights = [2.2] + [1] * chained + [2.2] * curved + [1.4] * noisy
    most = max(len(st["rows"]) + len(st.get("attempts", {})) for st in studies.values())
    fig, axes = plt.subplots(len(heights), len(studies),
                             figsize=(max(5.6 * len(studies), 6.4, 0.22 * most * len(studies)), 2.3 * sum(heights)),
                             squeeze=False, gridspec_kw={"height_ratios": heights})
    colors = {"supervised_only": "#7f7f7f", "real_truth": "#2ca02c", "real_pseudo": "#98df8a", "generated": "#1f77b4",
              "lasermix": "#ff7f0e", SIMULATED: "#9467bd", "round_trip_truth": "#17becf",
              "round_trip_pseudo": "#9edae5"}
    for ax, (backbone, study) in zip(axes[0], studies.items()):
        bars = [(ROW_LABELS[r], study["rows"][r], colors[r]) for r in study["rows"]]
        bars += [(f"GDA, {name}", rec, "#aec7e8") for name, rec in study.get("attempts", {}).items()]
        x = np.arange(len(bars))
        means = [100 * rec["miou_mean"] for _, rec, _ in bars]
        stds = [100 * (rec["miou_std"] or 0.0) for _, rec, _ in bars]
        ax.bar(x, means, 0.6, yerr=stds if any(stds) else None, capsize=4, color=[c for _, _, c in bars])
        for i, (_, rec, _) in enumerate(bars):
            seeds = [100 * v for v in rec["miou"]]
            ax.plot(np.full(len(seeds), x[i]) + np.linspace(-0.12, 0.12, len(seeds)), seeds, "k.", ms=4)
        ax.axhline(means[0], color="k", ls="--", lw=0.8)
        crowded = len(bars) > 15  # a sweep's many attempts: upright labels, one per bar
        ax.set_xticks(x, [label for label, _, _ in bars], rotation=90 if crowded else 25,
                      ha="center" if crowded else "right", fontsize=6 if crowded else 7)
        ax.set_ylabel(f"{study['evalset']} mIoU (%)" + (" (mean over severities)" if study["evalset"] != "val" else ""))
        n = len(study["seeds"])
        ax.set_title(f"{backbone} ({'mean +- std over ' + str(n) + ' seeds' if n > 1 else 'one seed'})", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    if chained:  # the chain from the ceiling to GDA: what each link costs, seed by seed
        for ax, (backbone, study) in zip(axes[1], studies.items()):
            links = [study["links"][k] for k in CHAIN]
            y = np.arange(len(CHAIN))
            ax.barh(y, [100 * ln["mean"] for ln in links], 0.5,
                    xerr=[100 * (ln["std"] or 0.0) for ln in links], capsize=4, color="#c5b0d5")
            for i, ln in enumerate(links):
                ax.plot([100 * v for v in ln["per_seed"]], np.full(len(ln["per_seed"]), y[i]), "k.", ms=4)
            ax.set_yticks(y, [f"{k}\n({LINKS[k][0]} - {LINKS[k][1]})" for k in CHAIN], fontsize=6)
            ax.axvline(0, color="k", lw=0.8)
            ax.invert_yaxis()
            ax.set_xlabel("mIoU points lost along the link (seed-paired)", fontsize=8)
            ax.grid(axis="x", alpha=0.3)
    if curved:  # how much of a scan the generator can make before it stops paying
        for ax, (backbone, study) in zip(axes[1 + chained], studies.items()):
            for i, curve in enumerate(study["strength_curves"].values()):
                color, cross = f"C{i}", curve["crossing_strength"]
                label = textwrap.fill(f"generator {curve['iterations']} iterations" + curve_words(curve)
                                      + (f", pays up to {cross:.2g}" if cross is not None else ""), 90)
                ax.errorbar(curve["strength"], [100 * g for g in curve["gain_mean"]],
                            yerr=[100 * (e or 0.0) for e in curve["gain_std"]], marker="o", capsize=3, color=color,
                            ls="--" if curve.get("labels") == "carried" else "-", label=label)
                if cross is not None:
                    ax.axvline(cross, color=color, ls=":", lw=1)
            ax.axhline(0, color="k", ls="--", lw=0.8)
            if "round_trip_pseudo" in study["rows"]:  # the pool's real scans, at the generator's image size
                ax.axhline(100 * study["rows"]["round_trip_pseudo"]["gain_over_supervised"]["mean"], color="#9edae5",
                           ls="-.", lw=1, label=ROW_LABELS["round_trip_pseudo"])
            ax.set_xscale("log")  # strengths > 0; what matters happens near the data
            ax.set_xlabel("sampling strength, log scale (~0: the generator's training scan, 1: a fresh sample)",
                          fontsize=8)
            ax.set_ylabel("gain over supervised only (points)", fontsize=8)
            ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(0.0, -0.22))  # below: many curves
            ax.grid(alpha=0.3)
    if noisy:  # how precise ranges must be: real scans, true labels, known range noise
        for ax, study in zip(axes[-1], studies.values()):
            curve = study["range_noise_curve"]
            ax.errorbar(curve["noise_std"], [100 * g for g in curve["gain_mean"]],
                        yerr=[100 * (e or 0.0) for e in curve["gain_std"]], marker="o", capsize=3, color="k",
                        label="real scans, true labels, range noise added")
            if curve["zero"] is not None:
                ax.axhline(100 * curve["zero"]["mean"], color="k", ls="-.", lw=1, label=f"no noise ({curve['zero']['row']})")
            if curve["crossing_noise"] is not None:
                ax.axvline(curve["crossing_noise"], color="k", ls=":", lw=1,
                           label=f"stops paying at {curve['crossing_noise']:.2g}")
            ax.axhline(0, color="k", ls="--", lw=0.8)
            ax.set_xscale("log")
            ax.set_xlabel("range noise, std of the encoded log-range (0.01 ~ 2.2 % of the range at KITTI's 80 m)",
                          fontsize=8)
            ax.set_ylabel("gain over supervised only (points)", fontsize=8)
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    setup = doc["setup"]
    fig.suptitle(f"GDA decomposition: {setup['percent']:g} % labels + N = {setup['scans']} scans\n"
                 f"({setup['domain']} samples for GDA, scored on {setup['evalset']})", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
