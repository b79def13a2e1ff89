"""omnilidar carry-labels: true labels for SDEdited scans, carried pixel by pixel from their sources."""

from __future__ import annotations

HELP = ("label each scan of a sample shard made with generator.sampling.strength < 1 with its source "
        "training scan's labels, pixel by pixel (the labeler-free counterpart of pseudo-label)")


def add_arguments(parser) -> None:
    parser.add_argument("--samples", required=True, help="sample shard (sample with strength < 1: has sources.json)")
    parser.add_argument("--out", required=True, help="label shard directory (labels/*.label, like pseudo-label's)")


def run(args) -> int:
    from omnilidar.generator.carried_labels import carry_source_labels

    side = carry_source_labels(args.samples, args.out)
    shares = [s["labelled_share"] for s in side["scans"] if s["labelled_share"] is not None]
    print(f"{len(side['scans'])} scans labelled from their sources (strength {side['strength']:g}); "
          f"labelled points {100 * sum(shares) / max(len(shares), 1):.1f} % -> {args.out}")
    return 0
