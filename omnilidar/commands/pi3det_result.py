"""omnilidar pi3det-result: one Pi3DET detection target (JSON with provenance + figure)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, seed_arg, settings_arg

HELP = "assemble a Pi3DET detection experiment (supervised-only vs GDA per detector, labeler AP) with its figure"


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--experiment", required=True, help="target name, e.g. pi3det_quadruped_1pct")
    parser.add_argument("--platform", required=True, choices=["drone", "quadruped"])
    parser.add_argument("--percent", type=int, required=True)
    parser.add_argument("--evaluations", nargs="+", required=True, help="evaluate-detector outputs of the runs")
    parser.add_argument("--labeler-evaluation", required=True, help="evaluate-detector output of the box labeler")
    parser.add_argument("--pseudo-boxes", nargs="*", default=[], help="pseudo-box shards used (counts, timings)")
    data_source_arg(parser)
    parser.add_argument("--out", required=True, help="result JSON")
    parser.add_argument("--figure", required=True, help="precision-recall figure with the AP table (PNG)")


def run(args) -> int:
    import json
    from pathlib import Path

    from omnilidar.downstream.det import experiments as ex
    from omnilidar.downstream.labeler_warning import warn_about_labeler
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.provenance import envelope
    from omnilidar.report.detection import pr_figure

    evals = [ex.read_evaluation(p) for p in args.evaluations]
    labeler = ex.read_evaluation(args.labeler_evaluation)
    sidecars = []
    for d in args.pseudo_boxes:
        side = Path(d) / "sidecar.json"
        if not side.is_file():
            raise InputError(d, "pseudo-box shard has no sidecar.json")
        sidecars.append(json.loads(side.read_text()))
    numbers = {
        "platform": args.platform, "label_percent": args.percent, "classes": evals[0]["classes"],
        "runs": ex.compare(evals, args.platform, args.percent),
        "labeler": ex.labeler_record(labeler, sidecars),
        "metric": ("KITTI 3D AP (OpenPCDet eval.py semantics, Pi3DET conversion: every box easy, no range "
                   "filter) at IoU 0.5: Car's second overlap set, Pedestrian's first; R11 and R40 in percent"),
        "val_frames": evals[0]["frames"],
    }
    numbers["labeler_check"] = ex.box_labeler_check(numbers["labeler"], numbers["runs"])
    doc = envelope(args.experiment, "pi3det-result", args.settings, {"seed": args.seed},
                   ex.timings(evals, labeler, sidecars), args.data_source, **numbers)
    write_text_atomic(args.out, json.dumps(doc, indent=1, default=str))
    pr_figure(ex.figure_panels(evals), args.figure,
              f"{args.experiment}: 3D precision-recall at IoU 0.5, supervised-only vs GDA")
    for detector, run in numbers["runs"].items():
        for cls in run["supervised_only"]["ap"]:
            print(f"{detector} {cls}: 3D R11@0.5 {run['supervised_only']['ap'][cls]['3d_R11@0.5']:.2f} -> GDA "
                  f"{run['gda']['ap'][cls]['3d_R11@0.5']:.2f}")
    warn_about_labeler(numbers["labeler_check"])
    print(f"result: {args.out}  figure: {args.figure}")
    return 0
