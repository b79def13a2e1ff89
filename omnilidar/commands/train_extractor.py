"""omnilidar train-extractor: self-train one metric extractor on the real training split."""

from __future__ import annotations

import json

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "train a generation-metric feature extractor (FRD/FRID/FSVD/FPVD/FPD) when no official weights are given"
# Run time reads (omnilidar.provenance).
DATA_FILES = ("workflow/schemas/evaluation.schema.yaml", "workflow/schemas/generator.schema.yaml")


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--extractor", required=True, choices=["frd", "frid", "fsvd", "fpvd", "fpd"])
    parser.add_argument("--index", required=True, help="segmentation dataset index JSON (SemanticKITTI, labelled)")
    parser.add_argument("--range-image", type=json.loads, required=True,
                        help="generator.range_image section (JSON): the geometry the metrics see")
    parser.add_argument("--out", required=True, help="self-trained extractor checkpoint (.pt)")


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.data.index import read_index
    from omnilidar.errors import InputError
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.extractors.training import train_extractor

    settings = validate(dict(args.settings), "evaluation.schema.yaml", source="--settings")
    ext = settings["extractors"]
    spec = range_image_spec({"range_image": validate({"range_image": args.range_image}, "generator.schema.yaml",
                                                     source="--range-image")["range_image"]})
    split = ext["training"]["split"]
    entries = [e for e in read_index(args.index)["splits"].get(split, []) if e.get("labels")]
    if not entries:
        raise InputError(args.index, f"split {split!r} has no labelled scans to train the extractor on")
    summary = train_extractor(args.extractor, ext["arch"][args.extractor], ext["training"], entries, spec,
                              args.seed, args.out)
    print(f"{args.extractor}: self-trained:{summary['config_hash']} loss {summary['loss_first']:.3f} -> "
          f"{summary['loss_last']:.3f} in {summary['seconds']:.0f} s -> {args.out}")
    return 0
