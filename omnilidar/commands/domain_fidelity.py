"""omnilidar domain-fidelity: what each effect does to real scans, per severity."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "fidelity report of the effects on real scans (fractions changed/lost/added, distributions, time)"


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="results JSON to write")
    parser.add_argument("--figure", required=True, help="figure (.png) to write")
    parser.add_argument("scans", nargs="*", help="real KITTI .bin scans (default: domains.fidelity.scans)")


def run(args) -> int:
    import json
    import time

    from omnilidar.config import validate
    from omnilidar.data.sensors import get_sensor
    from omnilidar.domains.fidelity import fidelity_report, plot_report, read_scans
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.data_source import configured_scans
    from omnilidar.provenance import envelope

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    cfg = settings["fidelity"]
    t0 = time.perf_counter()
    scans = read_scans(args.scans or cfg["scans"])
    report = fidelity_report(scans, get_sensor(cfg["sensor"]), cfg["effects"], cfg["seeds"])
    wall = time.perf_counter() - t0
    result = envelope("domain_fidelity", "domain-fidelity", cfg, {"seed": args.seed, "draws": cfg["seeds"]},
                      {"domain_fidelity": wall}, configured_scans([p for p, _ in scans]), scans=[p for p, _ in scans], effects=report)
    write_text_atomic(args.out, json.dumps(result, indent=1))
    plot_report(report, args.figure)
    print(f"fidelity report: {len(report)} effects on {len(scans)} scans in {wall:.1f} s -> {args.out}")
    return 0
