"""omnilidar make-subset: a deterministic label subset (one scan out of every k)."""

from __future__ import annotations

HELP = "write a label subset of a dataset split: one scan out of every 100/percent, as a JSON list"


def add_arguments(parser) -> None:
    parser.add_argument("--index", required=True, help="dataset index (data/index/<dataset>.json)")
    parser.add_argument("--split", default="train", help="split to subsample (default train)")
    parser.add_argument("--percent", type=float, required=True, help="percent of the split to keep (1 = every 100th)")
    parser.add_argument("--out", required=True, help="subset list (JSON)")


def run(args) -> int:
    from omnilidar.downstream.seg.subsets import make_subset, write_subset

    subset = make_subset(args.index, args.split, args.percent / 100.0)
    write_subset(subset, args.out)
    print(f"{subset['dataset']} {args.split}: {subset['num_scans']} of {subset['source_scans']} scans "
          f"(every {subset['every']}) -> {args.out}")
    return 0
