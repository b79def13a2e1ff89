"""omnilidar gda-decomposition: where GDA's effect is won or lost (results/gda_decomposition.json)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg

HELP = ("assemble the GDA decomposition: supervised-only, + real scans with true or pseudo-labels, "
        "+ generated scans, + LaserMix, over seeds")
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--evaluations", nargs="+", required=True,
                        help="evaluate-segmentor outputs of every row, backbone and seed")
    parser.add_argument("--evalset", default="val",
                        help="score on: val, or a corruption whose <corruption>/<severity> sets are averaged")
    parser.add_argument("--domain", help="domain of the generated row (default: the study's domain)")
    parser.add_argument("--attempt", action="append", default=[], metavar="NAME=EVALUATION",
                        help="evaluation of one run of a remedy tried on the generated row (repeatable)")
    parser.add_argument("--generator-iterations", type=int, default=None,
                        help="training iterations of the generator behind the generated row (labels strength curves)")
    parser.add_argument("--pool-labels", required=True, help="the labeler's labels of the real pool (their accuracy)")
    parser.add_argument("--labeler-evaluation", required=True, help="evaluate-segmentor output of the labeler")
    parser.add_argument("--attempt-labeler", action="append", default=[], metavar="NAME=EVALUATION",
                        help="evaluate-segmentor output of the own labeler of an attempt that has one (repeatable)")
    data_source_arg(parser)
    report_outputs_arg(parser, markdown=False)


def run(args) -> int:
    import json
    from pathlib import Path

    from omnilidar.config import validate
    from omnilidar.dicts import deep_merge
    from omnilidar.downstream.labeler_warning import warn_about_labeler
    from omnilidar.downstream.seg.experiments import labeler_against_students, labeler_quality, read_evaluation
    from omnilidar.downstream.seg.pseudo_label import SIDECAR
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.io.json_file import read_json
    from omnilidar.provenance import envelope
    from omnilidar.report import decomposition as dc

    settings = validate(dict(args.settings), "downstream.schema.yaml", source="--settings")
    requested = settings["experiments"]["gda_decomposition"]
    evals = [read_evaluation(p) for p in args.evaluations]
    def named(item: str, flag: str) -> tuple[str, dict]:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise InputError(None, f"{flag} takes NAME=EVALUATION, got {item!r}")
        return name, read_evaluation(path)

    attempts: dict[str, list[dict]] = {}
    for item in args.attempt:
        name, evaluation = named(item, "--attempt")
        attempts.setdefault(name, []).append(evaluation)
    attempt_labelers = {name: labeler_quality(evaluation)
                        for name, evaluation in (named(item, "--attempt-labeler") for item in args.attempt_labeler)}
    unknown = (set(attempts) | set(attempt_labelers)) - set(requested["attempts"])
    if unknown:
        raise InputError(None, f"attempt(s) {', '.join(sorted(unknown))} are not in experiments.gda_decomposition.attempts")
    studies = dc.decomposition(evals, attempts, args.evalset)
    for study in studies.values():
        curves = dc.strength_curves(study, requested["attempts"], args.generator_iterations)
        if curves:
            study["strength_curves"], study["strength_trend"] = curves, dc.strength_trend(curves)
        noise = dc.range_noise_curve(study, requested["attempts"])
        if noise:
            study["range_noise_curve"] = noise
    pool = read_json(Path(args.pool_labels) / SIDECAR, "pseudo-label folder has no sidecar.json")
    first = evals[0]
    setup = {"dataset": first["train"]["info"]["dataset"], "percent": first["train"]["info"]["percent"],
             "scans": requested["scans"], "domain": args.domain or requested["domain"], "evalset": args.evalset,
             "label_space": first["label_space"],
             # The regime every run of the study trained with: downstream keys + the study's overrides.
             "training": deep_merge({k: settings[k] for k in ("schedule", "voxel_size", "max_voxels", "max_points",
                                                              "models", "augmentation", "mixing")},
                                    requested["training"]),
             "training_overrides": requested["training"],
             "pool": first["train"]["info"].get("pool") or next(
                 (e["train"]["info"]["pool"] for e in evals if e["train"]["info"].get("pool")), None),
             "simulated_row": ("the domain builder's scans of the vehicle domain are the real scans (its scene "
                               "applies no effect): the simulated row is the real_truth row")
             if (args.domain or requested["domain"]) == "vehicle" else "the pool through the domain's scene"}
    timings = {f"train_{e['model']['backbone']}_{e['train']['info']['role']}_seed{e['seed']}": e["train"]["seconds"]
               for e in evals}
    experiment = "gda_decomposition" if args.evalset == "val" else f"gda_decomposition_{args.domain}"
    rows = list(next(iter(studies.values()))["rows"]) if studies else []
    labeler = labeler_quality(read_evaluation(args.labeler_evaluation))
    labeler_check = labeler_against_students(labeler, evals) if args.evalset == "val" else {
        "compared": False, "warning": None, "note": "the labeler is scored on val, this study on " + args.evalset}
    doc = envelope(
        experiment, "gda-decomposition", args.settings, {"seed": args.seed}, timings, args.data_source,
        setup=setup, rows=rows, links=dc.LINKS, attempts=requested["attempts"], backbones=studies,
        labeler=labeler, labeler_check=labeler_check, attempt_labelers=attempt_labelers,
        pool_pseudo_labels_against_truth=pool.get("accuracy_against_truth"),
        miou_convention="miou: semantic-kitti-api (absent classes count as 0)",
    )
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    dc.decomposition_figure(args.figure, doc)
    for backbone, study in studies.items():
        print(f"{backbone} (seeds {study['seeds']}):")
        for row, r in study["rows"].items():
            std = f" +- {100 * r['miou_std']:.2f}" if r["miou_std"] is not None else ""
            print(f"  {dc.ROW_LABELS[row]:<28} mIoU {100 * r['miou_mean']:.2f}{std}")
        for name, r in study["attempts"].items():
            std = f" +- {100 * r['miou_std']:.2f}" if r["miou_std"] is not None else ""
            own = (f" (own labeler: val mIoU {100 * attempt_labelers[name]['val_miou']:.2f})"
                   if name in attempt_labelers else "")
            print(f"  {'GDA, ' + name:<28} mIoU {100 * r['miou_mean']:.2f}{std}{own}")
        check = study["regime_check"]
        if check["set"]:
            print(f"  regime check on held-out train scans: ceiling gain {100 * check['ceiling_gain']['mean']:.2f} "
                  f"vs 2 std {100 * check['two_std']:.2f}: {'clears' if check['ceiling_clears_two_std'] else 'does not clear'}")
        scored = study["ceiling_on_evalset"]
        print(f"  on {study['evalset']} (reported only): ceiling gain {100 * scored['ceiling_gain']['mean']:.2f} "
              f"vs 2 std {100 * scored['two_std']:.2f}: {'clears' if scored['ceiling_clears_two_std'] else 'does not clear'}")
        for name in dc.CHAIN:
            if name in study["links"]:
                link = study["links"][name]
                std = f" +- {100 * link['std']:.2f}" if link["std"] is not None else ""
                print(f"  link {name:<11} costs {100 * link['mean']:.2f}{std} mIoU points ({' - '.join(dc.LINKS[name])})")
        print(f"  costliest link: {study['costliest_link']}")
        for curve in study.get("strength_curves", {}).values():
            gains = ", ".join(f"{st:g}: {100 * g:.2f}" for st, g in zip(curve["strength"], curve["gain_mean"]))
            cross = curve["crossing_strength"]
            print(f"  generator {curve['iterations']} it.{dc.curve_words(curve)}, gain by strength {gains}; stops paying at "
                  + (f"strength {cross:.2g}" if cross is not None else "no strength measured"))
        noise = study.get("range_noise_curve")
        if noise:
            gains = ", ".join(f"{n:g}: {100 * g:.2f}" for n, g in zip(noise["noise_std"], noise["gain_mean"]))
            cross = noise["crossing_noise"]
            print(f"  real scans with range noise, true labels, gain by noise std {gains}; stops paying at "
                  + (f"{cross:.2g}" if cross is not None else "no measured noise"))
    warn_about_labeler(labeler_check)
    print(f"result: {args.out}  figure: {args.figure}")
    return 0
