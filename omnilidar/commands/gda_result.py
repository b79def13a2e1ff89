"""omnilidar gda-result: one segmentation experiment target (JSON with provenance + figure)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, seed_arg, settings_arg

HELP = "assemble a segmentation GDA experiment (supervised-only vs GDA, mCE/mRR, weather subsets) with its figure"


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--experiment", required=True, help="target name, e.g. semkitti_1pct")
    parser.add_argument("--kind", required=True, choices=["semkitti", "semkittic", "nusc_beam32", "semanticstf"])
    parser.add_argument("--evaluations", nargs="+", required=True, help="evaluate-segmentor outputs")
    parser.add_argument("--pseudo-labels", nargs="*", default=[], help="pseudo-label shards used (for timings)")
    parser.add_argument("--labeler-evaluation", help="evaluate-segmentor output of the labeler (its own val scores)")
    data_source_arg(parser)
    parser.add_argument("--standin", action="store_true", help="the evaluation sets are a synthetic stand-in")
    parser.add_argument("--out", required=True, help="result JSON")
    parser.add_argument("--figure", required=True, help="per-class IoU figure (PNG)")


def run(args) -> int:
    import json
    from pathlib import Path

    from omnilidar.downstream.labeler_warning import warn_about_labeler
    from omnilidar.downstream.seg import experiments as ex
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.provenance import envelope
    from omnilidar.report.segmentation import iou_bars

    evals = [ex.read_evaluation(p) for p in args.evaluations]
    sidecars = []
    for d in args.pseudo_labels:
        side = Path(d) / "sidecar.json"
        if not side.is_file():
            raise InputError(d, "pseudo-label shard has no sidecar.json")
        sidecars.append(json.loads(side.read_text()))
    if args.kind in ("semkitti", "nusc_beam32"):
        numbers = {"runs": ex.compare(args.kind, evals)}
    elif args.kind == "semkittic":
        numbers = {"runs": ex.robustness_result(evals)}
    else:
        numbers = {"runs": ex.weather_result(evals)}
    first = evals[0]["train"]["info"]
    numbers.update({
        "label_space": evals[0]["label_space"],
        "label_percent": first["percent"],
        "generated_domains": sorted({d for e in evals for d in e["train"]["info"].get("domains", [])}),
        "miou_convention": "miou: semantic-kitti-api (absent classes count as 0); miou_nanmean: mmdet3d",
        "evaluation_sets": sorted(evals[0]["sets"]),
    })
    if args.labeler_evaluation:
        numbers["labeler"] = ex.labeler_quality(ex.read_evaluation(args.labeler_evaluation))
        numbers["labeler_check"] = ex.labeler_against_students(numbers["labeler"], evals)
    if args.kind == "semanticstf":
        numbers["synthetic_weather_standin"] = bool(args.standin)
        if args.standin:
            numbers["standin_note"] = ("SemanticSTF is not configured: the weather subsets are corrupted "
                                       "SemanticKITTI val sets (downstream.experiments.semanticstf.standin_sets); "
                                       "'rain' is the heavy wet-ground set since the corrupted sets have no rain")
    doc = envelope(args.experiment, "gda-result", args.settings, {"seed": args.seed},
                   ex.timings(evals, sidecars), args.data_source, **numbers)
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    title = f"{args.experiment}: per-class IoU, supervised-only vs GDA ({', '.join(numbers['generated_domains'])})"
    iou_bars(ex.figure_panels(args.kind, evals), args.figure, title)
    for backbone, run in numbers["runs"].items():
        if "miou_gain" in run and isinstance(run["miou_gain"], float):
            sup, gda = run["supervised_only"]["across_seeds"], run["gda"]["across_seeds"]
            spread = lambda a: "" if a["miou_std"] is None else f" +- {100 * a['miou_std']:.2f}"  # noqa: E731
            print(f"{backbone}: supervised-only {100 * sup['miou_mean']:.2f}{spread(sup)} "
                  f"-> GDA {100 * gda['miou_mean']:.2f}{spread(gda)} mIoU ({run['seeds']} seed(s))")
    if "labeler" in numbers:
        print(f"labeler (writes every pseudo-label): val mIoU {100 * numbers['labeler']['val_miou']:.2f}")
        warn_about_labeler(numbers["labeler_check"])
    print(f"result: {args.out}  figure: {args.figure}")
    return 0
