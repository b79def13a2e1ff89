"""omnilidar score: IoU and mIoU of SemanticKITTI prediction .label files made elsewhere."""

from __future__ import annotations

HELP = "score SemanticKITTI prediction .label files against ground-truth labels (semantic-kitti-api convention)"


def add_arguments(parser) -> None:
    parser.add_argument("--labels", required=True,
                        help="dataset root (sequences/NN/labels/*.label) or a flat folder of ground-truth .label files")
    parser.add_argument("--predictions", required=True,
                        help="root with sequences/NN/predictions/*.label (semantic-kitti-api layout) "
                             "or a flat folder of prediction .label files named like the labels")
    parser.add_argument("--sequences", nargs="*", default=None,
                        help="sequences to score (default: every sequence with a predictions folder)")
    parser.add_argument("--accuracy-convention", choices=["labelled", "semantic-kitti-api"], default="labelled",
                        help="accuracy denominator: every labelled point (default; a prediction of 0 is wrong) or, as "
                             "semantic-kitti-api's getacc, the labelled points predicted as a class")
    parser.add_argument("--out", default=None, help="scores as JSON (optional)")


def run(args) -> int:
    import json

    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.metrics.semantickitti_score import pair_files, score_files

    scores = score_files(pair_files(args.labels, args.predictions, args.sequences), args.accuracy_convention)
    for name, iou in scores["iou"].items():
        print(f"IoU {name:<14} {iou:.4f}")
    print(f"mIoU {scores['miou']:.4f} over 19 classes ({scores['files']} files, {scores['points']} points; "
          f"{scores['unknown_prediction_ids']} predictions with ids outside the learning map)")
    print(f"accuracy {scores['accuracy']:.4f} ({args.accuracy_convention} convention)")
    if args.out:
        write_text_atomic(args.out, json.dumps(scores, indent=1))
    return 0
