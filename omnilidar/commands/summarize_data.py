"""omnilidar summarize-data: scene statistics of every dataset beside real KITTI."""

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "scene statistics (classes, points per scan, range/elevation profiles) of indexed datasets"


def add_arguments(parser):
    parser.add_argument("indexes", nargs="+", help="dataset index JSON files (omnilidar index-dataset)")
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="summary JSON")
    parser.add_argument("--figure", required=True, help="summary figure (PNG)")


def _group_entries(index: dict) -> dict[str, list[dict]]:
    """Scans to summarise per group: one group per dataset, per platform for Pi3DET."""
    name = index["dataset"]
    groups: dict[str, list[dict]] = {}
    for split, entries in index["splits"].items():
        if name == "semantickitti" and split == "test":
            continue  # unlabelled; its geometry is like train's
        key = f"pi3det_{split.split('_')[0]}" if name == "pi3det" else name
        groups.setdefault(key, []).extend(entries)
    return groups


def _read(dataset: str, entry: dict):
    from omnilidar.io import kitti360, nuscenes, semantickitti

    if dataset == "nuscenes":
        return nuscenes.read_scan(entry["points"])
    if dataset == "kitti360":
        return kitti360.read_scan(entry["points"])
    return semantickitti.read_scan(entry["points"], entry.get("labels"))


def run(args):
    import json
    import time

    import numpy as np
    from tqdm import tqdm

    from omnilidar.data.index import read_index
    from omnilidar.data_source import record
    from omnilidar.data.reference_stats import semantickitti_class_fraction
    from omnilidar.data.synthetic.statistics import scan_statistics
    from omnilidar.io import semantickitti
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.provenance import envelope
    from omnilidar.report.data_summary import plot_data_summary

    start = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    max_scans = int(args.settings.get("max_scans", 200))
    groups, sources = {}, {}
    for path in args.indexes:
        index = read_index(path)
        sources[index["dataset"]] = record(index["root"], index.get("source") == "synthetic")
        for group, entries in _group_entries(index).items():
            if len(entries) > max_scans:  # a seeded, order-preserving subset
                entries = [entries[i] for i in np.sort(rng.choice(len(entries), max_scans, replace=False))]
            scans = (_read(index["dataset"], e) for e in tqdm(entries, desc=group, leave=False))
            groups[group] = scan_statistics(scans)
    reference = args.settings.get("reference_scans", [])
    if reference:
        groups["real_kitti_reference"] = scan_statistics(semantickitti.read_scan(p) for p in reference)

    summary = envelope(
        "data_summary", "summarize-data", args.settings, seeds={"subset": args.seed},
        timings={"summarize_s": round(time.perf_counter() - start, 3)},
        data_source=sources,
        groups=groups,
        reference_scans=reference,
        published_semantickitti_class_fraction=semantickitti_class_fraction(),
    )
    plot_data_summary(summary, args.figure)
    write_text_atomic(args.out, json.dumps(summary, indent=1))
    print(f"wrote {args.out} and {args.figure}")
