"""omnilidar index-dataset: list a dataset's scans and labels per split."""

HELP = "index a dataset root (real or synthetic) into a JSON list of scans per split"


def add_arguments(parser):
    parser.add_argument("dataset", choices=["semantickitti", "kitti360", "pi3det", "nuscenes"])
    parser.add_argument("--root", required=True, help="dataset root in its official layout")
    parser.add_argument("--out", required=True, help="index JSON to write")


def run(args):
    from omnilidar.data.index import build_index, write_index

    index = build_index(args.dataset, args.root)
    write_index(index, args.out)
    counts = ", ".join(f"{k}: {len(v)}" for k, v in index["splits"].items())
    print(f"indexed {args.dataset} at {args.root} ({counts})")
