"""omnilidar gda-budget: the GDA gain against the generator's training compute (results/gda_budget.json)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg

HELP = ("assemble the budget study: per generator training budget, its samples' quality and the GDA gain "
        "over supervised-only, seed by seed, beside pseudo-labelled real scans")
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--evaluations", nargs="+", required=True,
                        help="evaluations of the reference rows: supervised-only and pseudo-labelled real scans")
    parser.add_argument("--budget", action="append", required=True, metavar="ITERATIONS=GENERATOR=QUALITY",
                        help="one budget: its generator checkpoint and its sample-quality JSON (repeatable)")
    parser.add_argument("--run", action="append", required=True, metavar="ITERATIONS=EVALUATION",
                        help="evaluation of one GDA run trained on that budget's samples (repeatable)")
    parser.add_argument("--labeler-evaluation", required=True, help="evaluate-segmentor output of the labeler")
    data_source_arg(parser)
    report_outputs_arg(parser, markdown=False)


def _pairs(items: list[str], parts: int, flag: str) -> list[tuple[int, ...]]:
    from omnilidar.errors import InputError

    out = []
    for item in items:
        fields = item.split("=")
        if len(fields) != parts or not fields[0].isdigit() or not all(fields[1:]):
            raise InputError(None, f"{flag} {item!r}: expected {'='.join(['ITERATIONS'] + ['PATH'] * (parts - 1))}")
        out.append((int(fields[0]), *fields[1:]))
    return out


def run(args) -> int:
    import json

    import torch

    from omnilidar.config import validate
    from omnilidar.downstream.labeler_warning import warn_about_labeler
    from omnilidar.downstream.seg.experiments import (labeler_against_students, labeler_quality, read_evaluation,
                                                      runs_by_seed, seed_statistics)
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.io.json_file import read_json
    from omnilidar.provenance import envelope
    from omnilidar.report import budget as bg
    from omnilidar.report.decomposition import paired_difference

    settings = validate(dict(args.settings), "downstream.schema.yaml", source="--settings")
    requested = settings["experiments"]["gda_budget"]
    reference = [read_evaluation(p) for p in args.evaluations]
    roles = runs_by_seed(reference)
    if len(roles) != 1:
        raise InputError(None, f"the budget study runs one backbone; evaluations of {sorted(roles)} given")
    backbone, rows = next(iter(roles.items()))
    missing = {"supervised_only", "real_pseudo"} - set(rows)
    if missing:
        raise InputError(None, f"{backbone}: no {', '.join(sorted(missing))} evaluation given")
    supervised, real_pseudo = seed_statistics(rows["supervised_only"]), seed_statistics(rows["real_pseudo"])
    runs: dict[int, list[dict]] = {}
    for iterations, path in _pairs(args.run, 2, "--run"):
        runs.setdefault(iterations, []).append(read_evaluation(path))
    budgets = []
    for iterations, generator_path, quality_path in sorted(_pairs(args.budget, 3, "--budget")):
        if iterations not in runs:
            raise InputError(None, f"budget {iterations}: no --run evaluation given")
        try:
            payload = torch.load(generator_path, map_location="cpu", weights_only=True)
        except Exception as err:  # a missing or corrupt checkpoint: one line naming it
            raise InputError(generator_path, f"not a readable generator checkpoint: {err}") from None
        diffusion = payload.get("config", {}).get("diffusion", {})
        generator = {"path": generator_path, "iterations": payload.get("iterations"),
                     "train_seconds": payload.get("train_seconds"), "train_cpu_seconds": payload.get("train_cpu_seconds"),
                     # what the generator was trained as (checkpoints from before these options: the defaults)
                     "loss_weighting": diffusion.get("loss_weighting", "min_snr"), "prior": diffusion.get("prior", "zero")}
        quality = read_json(quality_path, "sample-quality JSON not found")
        docs = sorted(runs.pop(iterations), key=lambda d: d["seed"])
        budgets.append(bg.budget_record(iterations, generator, quality, docs, supervised, real_pseudo))
    if runs:
        raise InputError(None, f"--run evaluations of budget(s) {sorted(runs)} have no --budget")
    real_pseudo_gain = paired_difference(real_pseudo["miou"], supervised["miou"])
    levels = {"supervised_only": 0.0, "real_pseudo": real_pseudo_gain["mean"]}
    first = reference[0]["train"]["info"]
    setup = {"backbone": backbone, "percent": first["percent"], "scans": settings["experiments"]["gda_decomposition"]["scans"],
             "domain": settings["experiments"]["gda_decomposition"]["domain"], "budgets": sorted(requested["iterations"]),
             "loss_weighting": sorted({b["loss_weighting"] for b in budgets}),
             "prior": sorted({b["prior"] for b in budgets}),
             "x_axis": "generator training CPU-minutes (process CPU time of train-generator, all threads)"}
    labeler = labeler_quality(read_evaluation(args.labeler_evaluation))
    labeler_check = labeler_against_students(labeler, reference)
    timings = {f"generator_{b['iterations']}_cpu_minutes": round(b["train_cpu_minutes"], 3) for b in budgets}
    doc = envelope(
        "gda_budget", "gda-budget", args.settings, {"seed": args.seed, "runs": supervised["seeds"]}, timings,
        args.data_source, setup=setup, budgets=budgets,
        reference={"seeds": supervised["seeds"], "supervised_only": supervised, "real_pseudo": real_pseudo,
                   "real_pseudo_gain": real_pseudo_gain},
        trend=bg.trend(budgets, levels), labeler=labeler, labeler_check=labeler_check,
        miou_convention="miou: semantic-kitti-api (absent classes count as 0)",
    )
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    bg.budget_figure(args.figure, doc)
    print(f"{backbone}, seeds {supervised['seeds']}: supervised only {100 * supervised['miou_mean']:.2f}, "
          f"+N real with the labeler's labels gains {100 * real_pseudo_gain['mean']:.2f}")
    for b in budgets:
        gain = b["gain_over_supervised"]
        std = f" +- {100 * gain['std']:.2f}" if gain["std"] is not None else ""
        quality = ", ".join(f"{m} {v:.4g}" for m, v in b["quality"].items() if v is not None)
        print(f"  {b['iterations']:>6} it. ({b['train_cpu_minutes']:.1f} CPU-min): GDA gain {100 * gain['mean']:.2f}{std}"
              f"  [{quality}]")
    for name, cross in doc["trend"]["crossings"].items():
        where = (f"measured at {cross['first_measured_budget']} it." if cross["first_measured_budget"] is not None
                 else f"trend: ~{cross['trend_iterations']:.3g} it. ({cross['trend_cpu_minutes']:.3g} CPU-min)"
                 if cross["trend_cpu_minutes"] else cross.get("note", "not reached"))
        if cross.get("earliest_cpu_minutes"):
            where += f"; no earlier than ~{cross['earliest_iterations']:.3g} it. at the steepest slope the seeds allow"
        print(f"  reaches {name} ({100 * cross['level_gain']:.2f}): {where}")
    warn_about_labeler(labeler_check)
    print(f"result: {args.out}  figure: {args.figure}")
    return 0
