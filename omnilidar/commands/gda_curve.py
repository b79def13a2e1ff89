"""omnilidar gda-curve: downstream mIoU against the number of generated scans, with its compute."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg

HELP = "assemble mIoU against the number of generated scans and the seconds each point cost (results/gda_curve.json)"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--evaluations", nargs="+", required=True,
                        help="evaluate-segmentor outputs: the supervised-only run, --max-generated runs and "
                             "the real series' --max-pool runs")
    parser.add_argument("--samples", nargs="*", default=[], help="sample shards the runs drew from, in order")
    parser.add_argument("--pseudo-labels", nargs="*", default=[], help="their pseudo-label shards, same order")
    parser.add_argument("--labeler-evaluation", help="evaluate-segmentor output of the labeler (its own val scores)")
    data_source_arg(parser)
    report_outputs_arg(parser, markdown=False)


def run(args) -> int:
    import json

    from omnilidar.config import validate
    from omnilidar.downstream.labeler_warning import warn_about_labeler
    from omnilidar.downstream.seg.experiments import labeler_against_students, labeler_quality, read_evaluation
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.provenance import envelope
    from omnilidar.report import gda_curve as gc

    settings = validate(dict(args.settings), "downstream.schema.yaml", source="--settings")
    requested = settings["experiments"]["gda_curve"]
    evals = [read_evaluation(p) for p in args.evaluations]
    is_real = [e["train"].get("info", {}).get("role") in gc.SERIES_ROLES for e in evals]
    real = [e for e, r in zip(evals, is_real) if r]
    evals = [e for e, r in zip(evals, is_real) if not r]
    series = gc.series_rows(real)
    gda = any(e["train"].get("info", {}).get("role") == "gda" for e in evals)
    per_scan, measured = 0.0, 0
    if gda:
        per_scan, measured = gc.sampling_seconds_per_scan(args.samples)
    pseudo_per_scan, labeler_seconds = gc.pseudo_label_seconds_per_scan(args.pseudo_labels)
    rows = gc.curve_rows(evals, per_scan, pseudo_per_scan)
    if rows[-1]["generated_scans"] > measured and gda:
        raise InputError(args.samples[-1], f"the sample shards hold {measured} scans but a run used "
                                           f"{rows[-1]['generated_scans']}")
    first = evals[0]
    info = first["train"]["info"]
    domains = sorted({d for r in rows for d in r["domains"]})
    setup = {"backbone": first["model"]["backbone"], "dataset": info.get("dataset"), "percent": info.get("percent"),
             "domain": domains[0] if domains else requested["domain"], "label_space": first["label_space"],
             "selection": "first N generated scans: sample shards in order, scans in name order"}
    timings = {"sampling_per_scan": round(per_scan, 4), "pseudo_labels_per_scan": round(pseudo_per_scan, 4)}
    if labeler_seconds is not None:
        timings["labeler"] = labeler_seconds
    for ev in evals:
        count = gc.generated_count(ev)
        timings[f"train_{count}"] = ev["train"]["seconds"]
        timings[f"evaluate_{count}"] = ev["seconds"]
    labeler = {}
    if args.labeler_evaluation:
        labeler["labeler"] = labeler_quality(read_evaluation(args.labeler_evaluation))
        labeler["labeler_check"] = labeler_against_students(labeler["labeler"], evals)
    doc = envelope(
        "gda_curve", "gda-curve", args.settings, {"seed": args.seed}, timings, args.data_source,
        setup=setup, requested_generated_scans=sorted(requested["generated_scans"]),
        sampled_scans_measured=measured, sampling_seconds_source=(
            "sampling-loop seconds / generated scans, from each sample shard's timing.json"),
        total_note=gc.TOTAL_NOTE, miou_convention="miou: semantic-kitti-api (absent classes count as 0)",
        rows=rows, real_series=series,
        **labeler,
    )
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    gc.curve_figure(args.figure, doc)
    for role, points in series.items():
        print(f"{role}: " + ", ".join(f"{p['scans']} scans {100 * p['miou']:.2f}" for p in points))
    for r in rows:
        print(f"{r['generated_scans']:>6} generated: mIoU {100 * r['miou']:.2f}, {r['total_seconds']:.1f} s "
              f"(train {r['train_seconds']:.1f}, sampling {r['sampling_seconds']:.1f}, "
              f"pseudo-labels {r['pseudo_label_seconds']:.1f})")
    if labeler:
        warn_about_labeler(labeler["labeler_check"])
    print(f"result: {args.out}  figure: {args.figure}")
    return 0
