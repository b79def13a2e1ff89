"""omnilidar effects-tradeoff: accuracy against time of each effect's numerical knobs."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "accuracy/time curves of the effects' numerical knobs, with the chosen defaults marked"


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="results JSON to write")
    parser.add_argument("--figure", required=True, help="figure (.png) to write")
    parser.add_argument("scans", nargs="*", help="real KITTI .bin scan(s) (default: tradeoff.scans or the "
                                                 "first fidelity scan)")


def run(args) -> int:
    import json
    import time

    from omnilidar.config import validate
    from omnilidar.data.sensors import get_sensor
    from omnilidar.domains.fidelity import read_scans
    from omnilidar.domains.tradeoff import plot_tradeoff, tradeoff_study
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.data_source import configured_scans
    from omnilidar.provenance import envelope

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    cfg = settings["tradeoff"]
    paths = args.scans or cfg["scans"] or settings["fidelity"]["scans"][:1]
    t0 = time.perf_counter()
    scans = read_scans(paths)
    sensor = get_sensor(cfg["sensor"])
    studies = [tradeoff_study(scan, sensor, cfg["effects"], cfg["severity"], cfg["seeds"]) for _, scan in scans]
    wall = time.perf_counter() - t0
    result = envelope("effects_tradeoff", "effects-tradeoff", cfg, {"seed": args.seed, "curves": cfg["seeds"]},
                      {"effects_tradeoff": wall}, configured_scans([p for p, _ in scans]), scans=[p for p, _ in scans],
                      effects=studies[0], per_scan=studies[1:])
    write_text_atomic(args.out, json.dumps(result, indent=1))
    plot_tradeoff(studies[0], args.figure)
    print(f"tradeoff: {len(cfg['effects'])} effects on {len(scans)} scan(s) in {wall:.1f} s -> {args.out}")
    return 0
