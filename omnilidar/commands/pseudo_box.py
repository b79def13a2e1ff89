"""omnilidar pseudo-box: the fixed box labeler's boxes for one shard of generated scans, as Pi3DET infos."""

from __future__ import annotations

from omnilidar.commands._common import settings_arg, threads_arg

HELP = "pseudo-boxes (score >= downstream.det.labeler.score_threshold) for one generated sample shard, as Pi3DET infos"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml", "workflow/schemas/detection.schema.yaml")


def add_arguments(parser) -> None:
    settings_arg(parser)
    parser.add_argument("--labeler", required=True, help="labeler checkpoint (train-box-labeler)")
    parser.add_argument("--samples", required=True, help="generated sample shard (velodyne/*.bin)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="pseudo-box shard directory")


def run(args) -> int:
    import time

    from omnilidar.devices import resolve_device
    from omnilidar.downstream.det.dataset import DetScanDataset
    from omnilidar.downstream.det.predict import predict_frames
    from omnilidar.downstream.det.pseudo_boxes import sample_scans, write_shard
    from omnilidar.downstream.det.runs import det_settings, load_detector
    from omnilidar.devices import set_threads

    set_threads(args.threads)
    started = time.time()
    det = det_settings(args.settings)
    device = resolve_device(det["device"], "downstream.det.device")
    net, cfg, payload = load_detector(args.labeler, device)
    scans = [s for s in sample_scans(args.samples) if s.stat().st_size > 0]
    records = [{"points": str(s), "frame_id": s.stem, "boxes": [], "names": []} for s in scans]
    predictions, _, _ = predict_frames(net, DetScanDataset(records, cfg, det["voxels"]),
                                       det["labeler"]["batch_size"], device, log_every=10)
    labeler = {"detector": payload["detector"], "checkpoint": args.labeler, "train": payload.get("train", {})}
    sidecar = write_shard(args.samples, cfg.name, {p["frame_id"]: p for p in predictions},
                          det["labeler"]["score_threshold"], args.out, labeler, time.time() - started)
    print(f"pseudo-boxes for {sidecar['scans']} scans of {args.samples}: {sidecar['boxes']} -> {args.out}")
    return 0
