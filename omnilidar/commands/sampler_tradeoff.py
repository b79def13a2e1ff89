"""omnilidar sampler-tradeoff: what generation accuracy costs in time (samplers x steps)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg
from omnilidar.metrics.sample_sets import sample_set_arg

HELP = "measure per-domain JSD/MMD/feature metrics and seconds per scan for every sampler and step count"
DATA_FILES = ("workflow/schemas/evaluation.schema.yaml",)  # run time reads (omnilidar.provenance)

# A point is "recommended" when it is the fastest whose mean metric is within this factor of the best.
TOLERANCE = 1.10


def add_arguments(parser) -> None:
    settings_arg(parser)
    data_source_arg(parser)
    seed_arg(parser)
    parser.add_argument("--domains", required=True, help="the generator's training domains index")
    parser.add_argument("--reference", default=None,
                        help="domains index of the real scans every setting is scored against (each domain's "
                             "held-out set, data/domains_heldout/index.json); default: --domains, the training scans")
    parser.add_argument("--prompts", required=True)
    parser.add_argument("--checkpoint", required=True, help="full OmniLiDAR checkpoint")
    parser.add_argument("--student", default=None, help="its distilled student (with evaluation.tradeoff.student)")
    parser.add_argument("--default-sampler", default=None, metavar="NAME:STEPS",
                        help="the generator's own sampler (generator.sampling), measured beside the student")
    parser.add_argument("--weights", action="append", default=[], metavar="KIND=PATH")
    parser.add_argument("--effects", default=None, help="results/effects_tradeoff.json (optional)")
    parser.add_argument("--gda-curve", default=None,
                        help="results/gda_curve.json: downstream mIoU against the compute of generated scans")
    sample_set_arg(parser)  # sets SAMPLER-STEPS/DOMAIN
    report_outputs_arg(parser, markdown=False)


def effect_curves(path) -> list[dict]:
    """Error/time curves of the domain effects (one per effect and knob) from effects_tradeoff.json."""
    import json
    from pathlib import Path

    if not path or not Path(path).is_file():
        return []
    data = json.loads(Path(path).read_text())
    curves = []
    for effect, entry in (data.get("effects") or {}).items():
        key = entry.get("primary_error")
        knobs = dict.fromkeys(r["knob"] for r in entry.get("rows", []))
        for knob in knobs:
            rows = [r for r in entry["rows"] if r["knob"] == knob and key in r.get("errors", {})]
            rows = [r for r in rows if r["time_s"] == r["time_s"]]  # drop NaN times
            if rows:
                curves.append({"name": f"{effect}:{knob}", "error_key": key,
                               "values": [r["value"] for r in rows], "seconds": [r["time_s"] for r in rows],
                               "error": [r["errors"][key] for r in rows],
                               "default": [bool(r["is_default"]) for r in rows]})
    return curves


def describe_student(path: str, payload: dict) -> dict:
    """Which student the study scored: the config hash covers only the study's own settings, so
    the student's distillation settings, seed and training provenance travel with the result."""
    from omnilidar.checkpoints import provenance_hash

    return {"checkpoint": str(path), **payload["student"], "seed": payload.get("seed"),
            "distillation": payload["config"].get("distillation"),
            "provenance_hash": provenance_hash(payload["provenance"]) if payload.get("provenance") else None}


def reference_record(reference, training, domains: list[str]) -> dict:
    """Which real scans the study scores against: the index, each domain's source ("<dataset>
    <split>") beside the generator's training source, and held_out, true only where every domain's
    reference comes from another split than its training scans."""
    from omnilidar.metrics.generation import domain_sources

    sources, trained = domain_sources(reference, domains), domain_sources(training, domains)
    held_out = all(sources[d] is not None and trained[d] is not None and sources[d] != trained[d] for d in domains)
    return {"index": str(reference), "held_out": held_out, "sources": sources, "training_sources": trained}


def downstream_curve(path) -> tuple[list[dict], dict | None]:
    """(rows, setup) of a GDA curve file (mIoU against generated scans and their
    compute seconds); ([], None) when no file is given. A bad file is an InputError."""
    if not path:
        return [], None
    from omnilidar.report.gda_curve import ROW_FIELDS, read_curve

    doc = read_curve(path)
    keep = (*ROW_FIELDS, "pseudo_label_seconds")
    rows = [{k: r[k] for k in keep if k in r} for r in doc["rows"]]
    return rows, {"source": str(path), **(doc.get("setup") or {})}


def best_per_budget(points: list[dict], metrics: list[str]) -> dict:
    """{network evaluations: {metric: the point (solver and spacing) with the lowest mean}}."""
    best = {}
    for nfe in sorted({p["steps"] for p in points}):
        here = [p for p in points if p["steps"] == nfe]
        row = {}
        for m in metrics:
            ok = [p for p in here if p[f"mean_{m}"] is not None]
            if ok:
                pick = min(ok, key=lambda p: p[f"mean_{m}"])
                row[m] = {"sampler": pick["sampler"], "value": pick[f"mean_{m}"], "std": pick.get(f"std_{m}"),
                          "candidates": len(ok)}
        best[str(nfe)] = row
    return best


DECIDED_BY = ("JSD", "MMD")  # the metrics whose domain-by-domain verdicts decide whether a setting holds


def teacher_best(teachers: list[dict], m: str) -> dict | None:
    """The teacher's setting with the lowest mean ``m`` over domains (None: no setting scored it)."""
    ok = [p for p in teachers if p[f"mean_{m}"] is not None]
    return min(ok, key=lambda p: p[f"mean_{m}"]) if ok else None


def holds(point: dict, best: dict, m: str, name: str) -> dict:
    """Domain by domain, whether ``point`` holds ``best`` on ``m``: worse by at most two standard
    deviations of the difference (the two settings' seed-group spreads combined,
    :func:`omnilidar.metrics.generation.excess_in_spreads`)."""
    import math

    from omnilidar.metrics.generation import excess_in_spreads

    out = {}
    for d, mine in point["per_domain"].items():
        theirs = best["per_domain"][d]
        spreads = (mine.get(f"{m}_std"), theirs.get(f"{m}_std"))
        spread = math.hypot(*spreads) if None not in spreads else None
        excess = mine[m] - theirs[m]
        out[d] = {name: mine[m], "teacher": theirs[m], "excess": excess, "spread": spread,
                  "held": bool(spread is not None and excess_in_spreads(mine, theirs, m) <= 1.0)}
    return out


def teacher_settings_check(points: list[dict], metrics: list[str]) -> dict:
    """Every teacher setting against the teacher's best, by the student check's rule: {"sampler x
    steps": {metric: {"held": domains held, "of": domains, "missed": {domain: excess}}}}. It says
    whether the path a student learnt (DDIM x teacher_steps x teacher_substeps) holds the bar the
    student is held to."""
    teachers = [p for p in points if p["sampler"] != "student"]
    out = {}
    for p in teachers:
        row = {}
        for m in DECIDED_BY:
            best = teacher_best(teachers, m) if m in metrics else None
            if best is None or p[f"mean_{m}"] is None:
                continue
            verdicts = holds(p, best, m, "setting")
            row[m] = {"held": sum(v["held"] for v in verdicts.values()), "of": len(verdicts),
                      "missed": {d: v["excess"] for d, v in verdicts.items() if not v["held"]}}
        out[f"{p['sampler']} x {p['steps']}"] = row
    return out


def student_check(points: list[dict], metrics: list[str], default: tuple[str, int] | None) -> dict | None:
    """Whether the distilled student holds the teacher's quality: per metric, the teacher's best
    setting (lowest mean over domains) against the student, domain by domain; held where the
    student is worse by at most two standard deviations of the difference (the two settings' seed
    group spreads combined). JSD and MMD decide; the feature metrics are reported beside. With the
    generator's default sampler among the points, the student's speed-up over it."""
    student = next((p for p in points if p["sampler"] == "student"), None)
    teachers = [p for p in points if p["sampler"] != "student"]
    if student is None or not teachers:
        return None
    out = {"student_steps": student["steps"], "decided_by": list(DECIDED_BY), "metrics": {}}
    for m in metrics:
        best = teacher_best(teachers, m)
        if best is None or student[f"mean_{m}"] is None:
            continue
        per_domain = holds(student, best, m, "student")
        out["metrics"][m] = {"teacher_best": {"sampler": best["sampler"], "steps": best["steps"]},
                             "per_domain": per_domain,
                             "missed": {d: r["excess"] for d, r in per_domain.items() if not r["held"]}}
    decided = [out["metrics"][m] for m in out["decided_by"] if m in out["metrics"]]
    out["held"] = bool(decided) and all(not r["missed"] for r in decided)
    if default is not None:
        base = next((p for p in teachers if (p["sampler"], p["steps"]) == default), None)
        if base is not None and base["seconds_per_scan"] and student["seconds_per_scan"]:
            out["default_sampler"] = {"sampler": default[0], "steps": default[1],
                                      "seconds_per_scan": base["seconds_per_scan"]}
            out["speedup_over_default"] = base["seconds_per_scan"] / student["seconds_per_scan"]
    return out


def run(args) -> int:
    import time

    import numpy as np

    from omnilidar.config import validate
    from omnilidar.errors import InputError
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.devices import resolve_device
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.metrics.sampling_timing import TimedSetting, time_settings
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.extractors import METRIC_NAMES
    from omnilidar.metrics.extractors.weights import load_extractors, parse_pairs
    from omnilidar.metrics.generation import group_scores, real_domain_images, set_features
    from omnilidar.metrics.sample_sets import generated_set, parse_sample_sets
    from omnilidar.provenance import envelope
    from omnilidar.report.generation import collect_weights, pareto_front, tradeoff_figure, write_outputs

    settings = validate(dict(args.settings), "evaluation.schema.yaml", source="--settings")
    # Read before the long sampling study so that a bad curve file fails at once.
    downstream, downstream_setup = downstream_curve(args.gda_curve)
    cfg = settings["tradeoff"]
    feats = list(cfg["feature_metrics"])
    groups = int(cfg["seed_groups"])
    if cfg["scans"] < groups:
        raise InputError(None, f"evaluation.tradeoff: {cfg['scans']} scans cannot form {groups} seed groups")
    if cfg["student"] and not args.student:
        raise InputError(None, "evaluation.tradeoff.student is set: give the distilled student (--student)")
    metrics = ["JSD", "MMD", *feats]
    default = None
    if args.default_sampler:
        name, _, steps = args.default_sampler.partition(":")
        if not steps.isdigit():
            raise InputError(None, f"--default-sampler takes NAME:STEPS, got {args.default_sampler!r}")
        default = (name, int(steps))
        if int(steps) not in cfg["samplers"].get(name, []):
            raise InputError(None, f"the default sampler {args.default_sampler} is not among evaluation.tradeoff.samplers")
    weights = {k: v for k, v in parse_pairs(args.weights, "--weights").items() if METRIC_NAMES.get(k) in feats}
    extractors = load_extractors(weights, feats)
    device = resolve_device(settings["device"], "evaluation.device")
    den, payload = load_generator(args.checkpoint, device)
    spec = range_image_spec(payload["config"])
    cache = load_prompt_cache(args.prompts)
    sets = parse_sample_sets(args.samples)
    domains = cfg["domains"] or list(payload["domains"])
    reference = reference_record(args.reference or args.domains, args.domains, domains)
    real = {d: set_features(real_domain_images(reference["index"], d, spec.shape, settings["scans_per_set"]), spec,
                            extractors, settings["batch_size"], f"real {d}") for d in domains}
    settings_list = [(sampler, steps, den, payload) for sampler, steps_list in cfg["samplers"].items()
                     for steps in steps_list]
    student_record = None
    if cfg["student"]:
        student, student_payload = load_generator(args.student, device)
        if not student_payload.get("student"):
            raise InputError(args.student, "not a distilled student (distill_generator's output)")
        settings_list.append(("student", int(student_payload["student"]["steps"]), student, student_payload))
        student_record = describe_student(args.student, student_payload)
    t_all = time.perf_counter()

    def solver(sampler: str, model_payload: dict) -> str:
        """The student samples with the solver its checkpoint names, in its own steps."""
        return model_payload["student"]["sampler"] if sampler == "student" else sampler

    timing = cfg["timing"]
    print(f"timing every setting side by side: {timing['repeats']} x {timing['scans']} scans of {domains[0]}",
          flush=True)
    timed_seconds = time_settings([TimedSetting(m, mp, solver(sampler, mp), steps)
                                   for sampler, steps, m, mp in settings_list],
                                  cache, domains[0], timing["scans"], timing["repeats"], args.seed)
    points = []
    for (sampler, steps, model, model_payload), seconds in zip(settings_list, timed_seconds):
        per_domain, secs = {}, []
        for d in domains:
            gen, sec = generated_set(sets, f"{sampler}-{steps}/{d}", model, model_payload, cache, d, cfg["scans"],
                                     solver(sampler, model_payload), steps, args.seed, settings["batch_size"])
            scores = group_scores(real[d], set_features(gen, spec, extractors, settings["batch_size"]), extractors,
                                  groups, metrics)
            per_domain[d] = {**scores, "set_seconds_per_scan": sec}
            secs.append(sec)
        secs = [s for s in secs if s is not None]  # shards fully resumed record no time
        point = {"sampler": sampler, "steps": steps, "network_evaluations": steps, "seconds_per_scan": seconds,
                 "set_seconds_per_scan": float(np.mean(secs)) if secs else None, "per_domain": per_domain}
        for m in metrics:
            vals = [v[m] for v in per_domain.values()]
            stds = [v[f"{m}_std"] for v in per_domain.values()]
            point[f"mean_{m}"] = float(np.mean(vals)) if all(v is not None for v in vals) else None
            # Spread of the domain mean over the seed groups (the groups' errors are independent).
            point[f"std_{m}"] = (float(np.sqrt(np.sum(np.square(stds)))) / len(stds)
                                 if all(v is not None for v in stds) else None)
        points.append(point)
        print(f"{sampler} x {steps}: {point['seconds_per_scan']} s/scan, "
              + ", ".join(f"{m} {point[f'mean_{m}']}" for m in metrics), flush=True)
    recommended = {}
    timed = [p for p in points if p["seconds_per_scan"] is not None]
    for m in metrics:
        ok = [p for p in timed if p[f"mean_{m}"] is not None]
        flags = pareto_front([p["seconds_per_scan"] for p in ok], [p[f"mean_{m}"] for p in ok])
        for p in points:
            p.setdefault("pareto", {})[m] = False
        for p, f in zip(ok, flags):
            p["pareto"][m] = bool(f)
        if ok:
            best = min(p[f"mean_{m}"] for p in ok)
            good = [p for p in ok if p[f"mean_{m}"] <= best * TOLERANCE + 1e-12]
            pick = min(good, key=lambda p: p["seconds_per_scan"])
            recommended[m] = {"sampler": pick["sampler"], "steps": pick["steps"],
                              "seconds_per_scan": pick["seconds_per_scan"], "value": pick[f"mean_{m}"]}
    w, comparable = collect_weights({i: p["per_domain"] for i, p in enumerate(points)})
    result = envelope(
        "tradeoff", "sampler-tradeoff", settings, {"seed": args.seed, "seed_groups": groups},
        {"sampling_study": time.perf_counter() - t_all}, args.data_source,
        device_note=(f"seconds_per_scan: every setting timed side by side in this job on the device named above "
                     f"(median of {timing['repeats']} batches of {timing['scans']} {domains[0]} scans, round-robin "
                     "over the settings); set_seconds_per_scan: what the sets' own sampling jobs recorded, "
                     "possibly in other runs under other loads"),
        feature_metrics=feats, metrics=metrics, domains=domains, scans_per_setting=cfg["scans"],
        real_scans=settings["scans_per_set"], real_scans_per_domain={d: real[d].num_scans for d in domains},
        reference=reference, weights=w, comparable_with_paper=comparable, points=points,
        best_per_budget=best_per_budget(points, metrics), recommended=recommended,
        student_check=student_check(points, metrics, default),
        teacher_settings_check=teacher_settings_check(points, metrics),
        recommend_rule=f"fastest setting whose mean metric is within {TOLERANCE:.2f}x of the best",
        spread_rule=(f"each domain's metric is the mean over {groups} groups of scans with distinct sampling seeds; "
                     "std_<metric> is the spread over those groups of the mean over domains (the domains' group "
                     "spreads combined as independent)"),
        effects=effect_curves(args.effects), downstream=downstream, downstream_setup=downstream_setup,
        student=student_record,
    )
    write_outputs(result, args.out)
    tradeoff_figure(args.figure, result)
    print(f"recommended: {recommended}")
    return 0
