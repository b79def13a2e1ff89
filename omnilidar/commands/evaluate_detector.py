"""omnilidar evaluate-detector: KITTI AP (R11, R40) and recall of one detector on a platform's val frames."""

from __future__ import annotations

from omnilidar.commands._common import settings_arg, threads_arg

HELP = "score a trained detector on a Pi3DET platform's val frames (OpenPCDet eval.py semantics, Pi3DET conversion)"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml", "workflow/schemas/detection.schema.yaml")


def add_arguments(parser) -> None:
    settings_arg(parser)
    parser.add_argument("--checkpoint", required=True, help="detector payload (train-detector / train-box-labeler)")
    parser.add_argument("--index", required=True, help="Pi3DET dataset index")
    parser.add_argument("--split", default="val", help="split of the platform (<platform>_<split>)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="evaluation JSON")


def run(args) -> int:
    import json
    import time

    from omnilidar.devices import resolve_device
    from omnilidar.downstream.det.dataset import DetScanDataset
    from omnilidar.downstream.det.evaluate import score
    from omnilidar.downstream.det.predict import predict_frames, recall_rates
    from omnilidar.downstream.det.runs import det_settings, load_detector, platform_records
    from omnilidar.devices import set_threads
    from omnilidar.io.atomic import write_text_atomic

    set_threads(args.threads)
    started = time.time()
    det = det_settings(args.settings)
    device = resolve_device(det["device"], "downstream.det.device")
    net, cfg, payload = load_detector(args.checkpoint, device)
    records = platform_records(args.index, cfg.platform, args.split)
    dataset = DetScanDataset(records, cfg, det["voxels"])
    predictions, recall, per_frame = predict_frames(net, dataset, det["evaluation"]["batch_size"], device,
                                                    log_every=10)
    per_class = score(records, predictions, cfg.class_names)
    train = payload.get("train", {})
    doc = {"checkpoint": args.checkpoint, "detector": payload["detector"], "platform": cfg.platform,
           "split": f"{cfg.platform}_{args.split}", "frames": len(records), "classes": list(cfg.class_names),
           "ap": per_class, "recall": recall_rates(recall), "train": train,
           "timings": {"train_seconds": train.get("seconds"), "inference_seconds_per_frame": round(per_frame, 4),
                       "evaluate_seconds": round(time.time() - started, 2)}}
    write_text_atomic(args.out, json.dumps(doc, indent=1, default=str))
    summary = ", ".join(f"{c} 3D R11@0.5 {v['3d_R11@0.5']:.2f} R40 {v['3d_R40@0.5']:.2f}" for c, v in per_class.items())
    print(f"{payload['detector']} on {cfg.platform}_{args.split} ({len(records)} frames): {summary} -> {args.out}")
    return 0
