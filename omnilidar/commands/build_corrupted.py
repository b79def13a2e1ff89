"""omnilidar build-corrupted: one SemanticKITTI-C-style corrupted set."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "build one corrupted evaluation set (fog, wet_ground, snow, beam_missing at one severity)"
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    parser.add_argument("corruption", choices=["fog", "wet_ground", "snow", "beam_missing"])
    parser.add_argument("severity", choices=["light", "moderate", "heavy"])
    parser.add_argument("--index", required=True, help="dataset index JSON of the source (SemanticKITTI)")
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="set root to write (holds sequences/<seq>/...)")


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.domains.corruption import build_corrupted_set

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    sidecar = build_corrupted_set(args.corruption, args.severity, args.index, settings["corrupted"],
                                  args.seed, args.out)
    n_in = sum(s["num_points_in"] for s in sidecar["scans"])
    n_out = sum(s["num_points_out"] for s in sidecar["scans"])
    print(f"built {args.corruption}/{args.severity}: {len(sidecar['scans'])} scans, {n_in} -> {n_out} points "
          f"-> {args.out}")
    return 0
