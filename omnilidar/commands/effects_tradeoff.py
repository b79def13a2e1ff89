"""omnilidar effects-tradeoff: accuracy against time of each effect's numerical knobs."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "accuracy/time curves of the effects' numerical knobs, with the chosen defaults marked"
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="results JSON to write")
    parser.add_argument("--figure", required=True, help="figure (.png) to write")
    parser.add_argument("--index", default=None, help="SemanticKITTI index JSON: without scans, the study runs "
                                                       "on the first scan of fidelity.split")
    parser.add_argument("scans", nargs="*", help="KITTI .bin scan(s) (default: tradeoff.scans or the "
                                                 "first fidelity scan, else --index)")


def run(args) -> int:
    import json
    import time

    from omnilidar.config import validate
    from omnilidar.domains.fidelity import index_scan_paths, read_scans
    from omnilidar.domains.tradeoff import plot_tradeoff, tradeoff_study
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.data_source import configured_scans
    from omnilidar.lidar.sensors import get_sensor
    from omnilidar.provenance import envelope

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    cfg = settings["tradeoff"]
    paths, source = args.scans or cfg["scans"] or settings["fidelity"]["scans"][:1], "real"
    if not paths and args.index:
        paths, source = index_scan_paths(args.index, settings["fidelity"]["split"], 1)
    t0 = time.perf_counter()
    scans = read_scans(paths)
    sensor = get_sensor(cfg["sensor"])
    studies = [tradeoff_study(scan, sensor, cfg["effects"], cfg["severity"], cfg["seeds"]) for _, scan in scans]
    wall = time.perf_counter() - t0
    result = envelope("effects_tradeoff", "effects-tradeoff", cfg, {"seed": args.seed, "curves": cfg["seeds"]},
                      {"effects_tradeoff": wall}, source, scans=[p for p, _ in scans],
                      effects=studies[0], per_scan=studies[1:])
    write_text_atomic(args.out, json.dumps(result, indent=1))
    plot_tradeoff(studies[0], args.figure)
    print(f"tradeoff: {len(cfg['effects'])} effects on {len(scans)} scan(s) in {wall:.1f} s -> {args.out}")
    return 0
