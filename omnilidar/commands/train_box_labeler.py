"""omnilidar train-box-labeler: the fixed box labeler of one Pi3DET platform."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, segment_arg, settings_arg, threads_arg

HELP = ("the fixed box labeler of a Pi3DET platform: a user's OpenPCDet checkpoint (weights only) or the "
        "labeler detector trained once on 100 %% of the platform's real training frames")
DATA_FILES = ("workflow/schemas/downstream.schema.yaml", "workflow/schemas/detection.schema.yaml")


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--platform", required=True, choices=["drone", "quadruped"])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--index", help="Pi3DET dataset index: train on 100 %% of <platform>_train")
    source.add_argument("--checkpoint", help="a user's OpenPCDet checkpoint (model_state, loaded weights-only)")
    parser.add_argument("--model-config", default=None,
                        help="OpenPCDet-style yaml (default: downstream.det.detectors.<labeler.detector>.config)")
    parser.add_argument("--work-dir", default="work/detection/labeler", help="resumable training state (undeclared)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="labeler checkpoint (omnilidar detector payload)")
    segment_arg(parser)


def run(args) -> int:
    from omnilidar.downstream.det.labeler import import_labeler
    from omnilidar.downstream.det.runs import det_settings, platform_records, run_training
    from omnilidar.devices import set_threads

    set_threads(args.threads)
    det = det_settings(args.settings)
    detector = det["labeler"]["detector"]
    model_yaml = args.model_config or det["detectors"][detector]["config"]
    if args.checkpoint:
        summary = import_labeler(det, detector, args.platform, model_yaml, args.checkpoint, args.out)
        print(f"labeler {detector} {args.platform}: imported {args.checkpoint} -> {args.out}")
        return 0
    real = platform_records(args.index, args.platform, "train")
    info = {"role": "labeler", "platform": args.platform, "percent": 100.0, "subset_frames": len(real)}
    summary = run_training(det, det["labeler"]["schedule"], detector, args.platform, model_yaml, real, [],
                           args.out, args.work_dir, args.seed, info,
                           {"index": args.index, "model_config": model_yaml}, "train-box-labeler", with_mixing=False,
                           segment=args.segment)
    print(f"labeler {detector} {args.platform}: {summary['num_real']} real frames, {summary['iterations']} "
          f"iterations, {summary['seconds']} s -> {args.out}")
    return 0
