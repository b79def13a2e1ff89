"""omnilidar sample-quality: a generator's samples against held-out real scans (FRD, JSD, MMD)."""

from __future__ import annotations

import json

HELP = "score generated scans against held-out real scans (FRD with an extractor, JSD, MMD)"
DATA_FILES = ("workflow/schemas/generator.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    parser.add_argument("--subset", required=True, help="held-out real scans (make-subset JSON)")
    parser.add_argument("--samples", nargs="+", required=True, help="sample shards of the generator scored")
    parser.add_argument("--scans", type=int, required=True, help="scans compared per set (the first of each)")
    parser.add_argument("--metrics", nargs="+", default=["FRD", "JSD", "MMD"], choices=["FRD", "JSD", "MMD"])
    parser.add_argument("--weights", action="append", default=[], metavar="KIND=PATH",
                        help="feature extractor of a Frechet metric (frd=PATH)")
    parser.add_argument("--range-image", type=json.loads, required=True,
                        help="generator.range_image section (JSON): the geometry both sets are seen in")
    parser.add_argument("--out", required=True, help="scores (JSON)")


def run(args) -> int:
    from pathlib import Path

    from omnilidar.config import validate
    from omnilidar.data.subsets import read_subset
    from omnilidar.errors import InputError
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.metrics.extractors.weights import load_extractors, parse_pairs
    from omnilidar.metrics.generation import entry_images, generation_metrics
    from omnilidar.metrics.sample_sets import load_sample_set

    if args.scans < 2:
        raise InputError(None, f"--scans {args.scans}: the metrics compare sets of at least 2 scans")
    spec = range_image_spec({"range_image": validate({"range_image": args.range_image}, "generator.schema.yaml",
                                                     source="--range-image")["range_image"]})
    subset = read_subset(args.subset)
    if subset["num_scans"] < args.scans:
        raise InputError(args.subset, f"holds {subset['num_scans']} scans, --scans {args.scans} asked")
    real = entry_images(subset["entries"][: args.scans], spec)
    generated, seconds_per_scan = load_sample_set([Path(s) for s in args.samples], args.scans, "generated")
    extractors = load_extractors(parse_pairs(args.weights, "--weights"), args.metrics)
    scores = generation_metrics(real, generated, spec, extractors)
    doc = {"metrics": {m: scores.get(m) for m in args.metrics}, "MMD_1e4": scores.get("MMD_1e4"),
           "n_real": scores["n_real"], "n_generated": scores["n_generated"], "weights": scores["weights"],
           "notes": scores["notes"], "real": args.subset, "samples": list(args.samples),
           "sampling_seconds_per_scan": seconds_per_scan,
           "range_image": {"height": spec.height, "width": spec.width}}
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    print(", ".join(f"{m} {v:.4g}" if v is not None else f"{m} undefined" for m, v in doc["metrics"].items())
          + f" ({args.scans} generated vs {args.scans} held-out real scans) -> {args.out}")
    return 0
