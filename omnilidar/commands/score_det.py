"""omnilidar score-det: KITTI 3D detection AP of prediction files made elsewhere."""

from __future__ import annotations

HELP = "score KITTI-format detection files against label_2 files or Pi3DET infos (OpenPCDet eval.py AP, R11 and R40)"


def add_arguments(parser) -> None:
    parser.add_argument("--predictions", required=True,
                        help="folder of <frame>.txt KITTI label files with a 16th column, the score")
    labels = parser.add_mutually_exclusive_group(required=True)
    labels.add_argument("--labels", help="folder of KITTI label_2 <frame>.txt ground-truth files")
    labels.add_argument("--infos", help="Pi3DET info pickle: every box easy, Vehicle -> Car, no range filter "
                                        "(predictions in omnilidar.metrics.kitti_ap.pi3det_annos' camera frame)")
    parser.add_argument("--classes", nargs="+", default=None,
                        help="KITTI classes to score (default: those of the ground truth among Car, Pedestrian, "
                             "Cyclist, Van, Person_sitting, Truck)")
    parser.add_argument("--out", default=None, help="AP, curves and OpenPCDet's dict as JSON (optional)")


def run(args) -> int:
    import json
    from pathlib import Path

    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.metrics import kitti_ap

    predictions = Path(args.predictions)
    if not predictions.is_dir():
        raise InputError(predictions, "predictions folder not found")
    if args.labels:
        folder = Path(args.labels)
        if not folder.is_dir():
            raise InputError(folder, "labels folder not found")
        frames = {p.stem: kitti_ap.label_file_anno(p) for p in sorted(folder.glob("*.txt"))}
        if not frames:
            raise InputError(folder, "holds no .txt label files")
    else:
        from omnilidar.io import pi3det

        frames = {}
        for info in pi3det.read_infos(args.infos):
            annos = info.get("annos") or {}
            frames[str(info["frame_id"])] = kitti_ap.pi3det_annos(annos.get("gt_boxes_lidar", []),
                                                                  list(annos.get("gt_names", [])))
    extra = sorted({p.stem for p in predictions.glob("*.txt")} - set(frames))
    if extra:
        raise InputError(predictions / f"{extra[0]}.txt", "has no ground-truth frame of that name")
    gt, dt = [], []
    for frame, anno in frames.items():
        path = predictions / f"{frame}.txt"
        if not path.is_file():
            raise InputError(path, f"missing: every ground-truth frame needs a prediction file (frame {frame})")
        gt.append(anno)
        dt.append(kitti_ap.label_file_anno(path, need_score=True))
    classes = args.classes or [c for c in kitti_ap.CLASS_NAMES if any(c in a["name"] for a in gt)]
    if not classes:
        raise InputError(args.labels or args.infos, f"no box of a KITTI class ({', '.join(kitti_ap.CLASS_NAMES)})")
    result = kitti_ap.kitti_eval(gt, dt, classes)
    print(result["result_str"], end="")
    print(f"{len(gt)} frames, classes {', '.join(classes)}")
    if args.out:
        write_text_atomic(args.out, json.dumps({"frames": len(gt), "classes": classes,
                                                **{k: v for k, v in result.items() if k != "result_str"}}, indent=1))
    return 0
