"""omnilidar evaluate-segmentor: per-class IoU, mIoU (both conventions) and accuracy."""

from __future__ import annotations

from omnilidar.commands._common import settings_arg, threads_arg

HELP = "evaluate a segmentor on the official val split and/or folders of labelled scans (per-class IoU, mIoU, accuracy)"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    parser.add_argument("--checkpoint", required=True, help="segmentor checkpoint from train-segmentor")
    parser.add_argument("--index", help="dataset index whose --split is evaluated as set 'val'")
    parser.add_argument("--split", default="val", help="split of --index (default val)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=DIR",
                        help="an extra set: a SemanticKITTI-layout folder of labelled scans (repeatable)")
    parser.add_argument("--subset-set", dest="subset_sets", action="append", default=[], metavar="NAME=SUBSET",
                        help="an extra set: the labelled scans of a subset list (make-subset), e.g. held-out "
                             "train scans (repeatable)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="scores (JSON)")


def run(args) -> int:
    import json
    import time

    import torch

    from omnilidar.config import validate
    from omnilidar.data.index import read_index
    from omnilidar.downstream.seg.dataset import records_from_entries
    from omnilidar.downstream.seg.evaluate import (
        evaluate_records,
        label_space_of,
        load_segmentor,
        semantickitti_dir_records,
    )
    from omnilidar.data.subsets import read_subset
    from omnilidar.devices import set_threads
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic

    set_threads(args.threads)
    settings = validate(dict(args.settings), "downstream.schema.yaml", source="--settings")
    backend, device = settings["backend"], settings["device"]
    started = time.time()
    sets: dict[str, list[dict]] = {}
    if args.index:
        index = read_index(args.index)
        if args.split not in index["splits"]:
            raise InputError(args.index, f"has no split {args.split!r}")
        sets["val"] = records_from_entries(index["splits"][args.split], index["dataset"])
    for item in args.sets:
        name, sep, folder = item.partition("=")
        if not sep or not name:
            raise InputError(None, f"--set must be NAME=DIR, got {item!r}")
        sets[name] = semantickitti_dir_records(folder)
    for item in args.subset_sets:
        name, sep, path = item.partition("=")
        if not sep or not name:
            raise InputError(None, f"--subset-set must be NAME=SUBSET, got {item!r}")
        subset = read_subset(path)
        sets[name] = records_from_entries(subset["entries"], subset["dataset"])
    if not sets:
        raise InputError(None, "nothing to evaluate: give --index and/or --set")
    with torch.no_grad():  # a context, not a global switch: callers may run in-process
        model, payload = load_segmentor(args.checkpoint, backend, device)
        space = label_space_of(payload)
        scores = {}
        for name, records in sets.items():
            scores[name] = evaluate_records(model, records, space, payload["voxel_size"],
                                            settings["evaluation"]["batch_size"])
            print(f"{name}: mIoU {100 * scores[name]['miou']:.2f} (nanmean {100 * scores[name]['miou_nanmean']:.2f}), "
                  f"accuracy {100 * scores[name]['accuracy']:.2f}, {scores[name]['num_scans']} scans", flush=True)
    doc = {
        "checkpoint": args.checkpoint, "model": payload["model"], "label_space": space.name,
        "class_names": list(space.class_names), "voxel_size": payload["voxel_size"], "seed": payload["seed"],
        "train": payload.get("train", {}), "sets": scores, "seconds": round(time.time() - started, 2),
    }
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    return 0
