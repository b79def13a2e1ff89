"""omnilidar pseudo-label: label one sample shard with the fixed labeler."""

from __future__ import annotations

from omnilidar.commands._common import settings_arg, threads_arg

HELP = "pseudo-label one shard of generated scans (.label files in raw SemanticKITTI ids)"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    parser.add_argument("--labeler", required=True, help="labeler checkpoint from train-labeler")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--samples", help="sample shard directory (velodyne/*.bin)")
    source.add_argument("--pool", help="a pool of real scans (make-subset --exclude); records accuracy against truth")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="pseudo-label shard directory (appears only when complete)")


def run(args) -> int:
    import torch

    from omnilidar.config import validate
    from omnilidar.downstream.seg.evaluate import load_segmentor
    from omnilidar.downstream.seg.pseudo_label import pseudo_label_pool, pseudo_label_shard
    from omnilidar.devices import set_threads

    set_threads(args.threads)
    section = validate({"labeler": dict(args.settings)}, "downstream.schema.yaml", source="--settings")["labeler"]
    with torch.no_grad():  # a context, not a global switch: callers may run in-process
        model, payload = load_segmentor(args.labeler, section["backend"], section["device"])
        label = pseudo_label_pool if args.pool else pseudo_label_shard
        side = label(model, payload, args.pool or args.samples, args.out, section["batch_size"])
    print(f"{len(side['scans'])} scans pseudo-labelled in {side['seconds']} s -> {args.out}")
    if side["accuracy_against_truth"]:
        print(f"pseudo-labels against the true labels: mIoU {100 * side['accuracy_against_truth']['miou']:.2f}")
    return 0
