"""omnilidar domain-fidelity: what each effect does to KITTI-format scans, per severity."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "fidelity report of the effects on scans (fractions changed/lost/added, distributions, time)"
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="results JSON to write")
    parser.add_argument("--figure", required=True, help="figure (.png) to write")
    parser.add_argument("--index", default=None, help="SemanticKITTI index JSON: without scans, the report runs "
                                                       "on the first fidelity.max_scans scans of fidelity.split")
    parser.add_argument("scans", nargs="*", help="KITTI .bin scans (default: domains.fidelity.scans, else --index)")


def run(args) -> int:
    import json
    import time

    from omnilidar.config import validate
    from omnilidar.domains.fidelity import fidelity_report, index_scan_paths, plot_report, read_scans
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.data_source import configured_scans
    from omnilidar.lidar.sensors import get_sensor
    from omnilidar.provenance import envelope

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    cfg = settings["fidelity"]
    paths = args.scans or cfg["scans"]
    source = configured_scans(paths)
    if not paths and args.index:
        paths, source = index_scan_paths(args.index, cfg["split"], cfg["max_scans"])
    t0 = time.perf_counter()
    scans = read_scans(paths)
    report = fidelity_report(scans, get_sensor(cfg["sensor"]), cfg["effects"], cfg["seeds"])
    wall = time.perf_counter() - t0
    result = envelope("domain_fidelity", "domain-fidelity", cfg, {"seed": args.seed, "draws": cfg["seeds"]},
                      {"domain_fidelity": wall}, source, scans=[p for p, _ in scans], effects=report)
    write_text_atomic(args.out, json.dumps(result, indent=1))
    plot_report(report, args.figure)
    print(f"fidelity report: {len(report)} effects on {len(scans)} scans in {wall:.1f} s -> {args.out}")
    return 0
