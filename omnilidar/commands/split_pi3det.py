"""omnilidar split-pi3det: deterministic train/val info lists of a Pi3DET platform, by sequence."""

from __future__ import annotations

HELP = "write <platform>_infos_{train,val}.pkl of a Pi3DET platform: sorted sequences, every k-th to val"


def add_arguments(parser) -> None:
    parser.add_argument("root", help="Pi3DET dataset root (point paths in the infos are relative to it)")
    parser.add_argument("--platform", required=True, help="platform folder, e.g. drone or quadruped")
    parser.add_argument("--val-every", type=int, default=5,
                        help="every k-th sorted sequence goes to val, starting with the first (default 5)")
    parser.add_argument("--infos", nargs="*", default=None,
                        help="info pickles to split (default: <platform>/<platform>_infos_*.pkl but train/val)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing train/val lists")


def run(args) -> int:
    from omnilidar.data.pi3det_splits import write_split_lists

    sequences = write_split_lists(args.root, args.platform, args.val_every, args.infos, args.overwrite)
    for split in ("train", "val"):
        print(f"{args.platform} {split}: {len(sequences[split])} sequences ({', '.join(sequences[split])})")
    return 0
