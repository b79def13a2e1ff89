"""omnilidar make-subset: a deterministic label subset (one scan out of every k)."""

from __future__ import annotations

HELP = "write a label subset of a dataset split: one scan out of every 100/percent, as a JSON list"


def add_arguments(parser) -> None:
    parser.add_argument("--index", required=True, help="dataset index (data/index/<dataset>.json)")
    parser.add_argument("--split", default="train", help="split to subsample (default train)")
    parser.add_argument("--percent", type=float, help="percent of the split to keep (1 = every 100th)")
    parser.add_argument("--exclude", metavar="SUBSET", nargs="+",
                        help="write a pool instead: --count scans of the split outside these subsets, evenly spread")
    parser.add_argument("--count", type=int, help="scans in the pool (with --exclude)")
    parser.add_argument("--heldout", metavar="SUBSET",
                        help="with --exclude: leave out every sequence of this held-out set too")
    parser.add_argument("--whole-sequences", action="store_true",
                        help="with --exclude: a held-out set instead, --count scans of the split's last "
                             "sequences that hold no excluded scan")
    parser.add_argument("--out", required=True, help="subset list (JSON)")


def run(args) -> int:
    from omnilidar.data.subsets import make_heldout, make_pool, make_subset, read_subset, write_subset
    from omnilidar.errors import InputError

    if (args.exclude is None) == (args.percent is None) or (args.exclude is None) != (args.count is None):
        raise InputError(None, "give either --percent, or --exclude SUBSET with --count N")
    if (args.heldout or args.whole_sequences) and not args.exclude:
        raise InputError(None, "--heldout and --whole-sequences go with --exclude SUBSET --count N")
    if args.heldout and args.whole_sequences:
        raise InputError(None, "give --heldout (a pool outside a held-out set) or --whole-sequences (a held-out set)")
    if args.exclude:
        taken = [read_subset(path) for path in args.exclude]
        excluded = {"entries": [e for doc in taken for e in doc["entries"]], "num_scans": sum(d["num_scans"] for d in taken)}
        names = " + ".join(args.exclude)
        if args.whole_sequences:
            held = make_heldout(args.index, args.split, excluded, args.count, names)
            write_subset(held, args.out)
            print(f"{held['dataset']} {args.split}: {held['num_scans']} held-out scans of sequences "
                  f"{', '.join(held['excludes']['sequences'])} -> {args.out}")
            return 0
        heldout = read_subset(args.heldout) if args.heldout else None
        pool = make_pool(args.index, args.split, excluded, args.count, names, heldout, args.heldout)
        write_subset(pool, args.out)
        outside = names + (f" and the sequences of {args.heldout}" if heldout else "")
        print(f"{pool['dataset']} {args.split}: pool of {pool['num_scans']} scans outside {outside} -> {args.out}")
        return 0
    subset = make_subset(args.index, args.split, args.percent / 100.0)
    write_subset(subset, args.out)
    print(f"{subset['dataset']} {args.split}: {subset['num_scans']} of {subset['source_scans']} scans "
          f"(every {subset['every']}) -> {args.out}")
    return 0
