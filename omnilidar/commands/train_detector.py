"""omnilidar train-detector: one detection run (supervised-only or GDA) from scratch."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, segment_arg, settings_arg, threads_arg

HELP = ("train Voxel R-CNN or PV-RCNN from scratch on a label subset of a Pi3DET platform's training frames, "
        "plus pseudo-boxed generated scans for GDA")
DATA_FILES = ("workflow/schemas/downstream.schema.yaml", "workflow/schemas/detection.schema.yaml")


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--detector", required=True, choices=["voxel_rcnn", "pv_rcnn"])
    parser.add_argument("--platform", required=True, choices=["drone", "quadruped"])
    parser.add_argument("--index", required=True, help="Pi3DET dataset index (index-dataset JSON)")
    parser.add_argument("--percent", type=float, required=True, help="label subset: one frame out of every 100/pct")
    parser.add_argument("--model-config", default=None,
                        help="OpenPCDet-style yaml (default: downstream.det.detectors.<detector>.config)")
    parser.add_argument("--samples", nargs="*", default=[], help="generated sample shards (GDA)")
    parser.add_argument("--pseudo-boxes", nargs="*", default=[], help="their pseudo-box shards, same order")
    parser.add_argument("--work-dir", default="work/detection", help="resumable training state (undeclared)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="detector checkpoint (weights-only loadable)")
    segment_arg(parser)


def run(args) -> int:
    from omnilidar.downstream.det.dataset import records_from_entries
    from omnilidar.downstream.det.pseudo_boxes import generated_records
    from omnilidar.downstream.det.runs import det_settings, run_training
    from omnilidar.downstream.det.subsets import make_det_subset
    from omnilidar.devices import set_threads
    from omnilidar.errors import InputError

    set_threads(args.threads)
    det = det_settings(args.settings)
    subset = make_det_subset(args.index, args.platform, args.percent / 100.0)
    real = records_from_entries(subset["entries"])
    generated, empty = generated_records(args.samples, args.pseudo_boxes)
    if args.samples and not generated:
        raise InputError(args.samples[0], "the generated shards hold no non-empty scan")
    info = {"role": "gda" if args.samples else "supervised_only", "platform": args.platform,
            "percent": args.percent, "subset_frames": subset["num_scans"], "subset_boxes": subset["num_boxes"],
            "source_frames": subset["source_scans"], "empty_generated": empty}
    inputs = {"index": args.index, "samples": list(args.samples), "pseudo_boxes": list(args.pseudo_boxes)}
    model_yaml = args.model_config or det["detectors"][args.detector]["config"]
    summary = run_training(det, det["schedule"], args.detector, args.platform, model_yaml, real, generated,
                           args.out, args.work_dir, args.seed, info, inputs | {"model_config": model_yaml},
                           "train-detector", with_mixing=bool(args.samples), segment=args.segment)
    print(f"{args.detector} {args.platform} {info['role']}: {summary['num_real']} real + {summary['num_generated']} "
          f"generated frames, {summary['iterations']} iterations, {summary['seconds']} s -> {args.out}")
    return 0
