"""omnilidar convert-nuscenes: the nuScenes release (devkit tables) -> our nuScenes layout."""

from __future__ import annotations

HELP = "convert a nuScenes release (devkit JSON tables, lidarseg) to the <split>/samples/LIDAR_TOP layout"


def add_arguments(parser) -> None:
    parser.add_argument("--tables", required=True,
                        help="the release's table folder, e.g. /data/nuscenes/v1.0-trainval (its parent is the dataroot)")
    parser.add_argument("--out", required=True, help="new dataset root to write (datasets.nuscenes.root)")
    parser.add_argument("--version", default=None, help="v1.0-trainval or v1.0-mini (default: the table folder's name)")
    parser.add_argument("--splits-file", default=None,
                        help="the devkit's nuscenes/utils/splits.py (default: the installed devkit's)")
    parser.add_argument("--copy", action="store_true", help="copy the files instead of linking them")


def run(args) -> int:
    from omnilidar.errors import InputError
    from omnilidar.io.nuscenes_tables import devkit_splits_file, plan_frames, read_split_lists, write_layout

    splits_file = args.splits_file or devkit_splits_file()
    if splits_file is None:
        raise InputError(None, "official split lists not found: install nuscenes-devkit (pip install --no-deps "
                               "nuscenes-devkit is enough) or pass --splits-file nuscenes/utils/splits.py")
    frames = plan_frames(args.tables, read_split_lists(splits_file), args.version)
    counts = write_layout(frames, args.out, copy=args.copy)
    for split, c in sorted(counts.items()):
        print(f"{split}: {c['scans']} key frames, {c['labelled']} with lidarseg -> {args.out}/{split}")
    return 0
