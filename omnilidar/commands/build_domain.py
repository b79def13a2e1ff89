"""omnilidar build-domain: one shard of a domain (its scene spec applied to source scans)."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "build one shard of a domain: range images (.npz), point files, labels and a sidecar"
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    parser.add_argument("domain", help="domain key of the domains section (vehicle, fog, ...)")
    parser.add_argument("--index", required=True, help="dataset index JSON of the domain's source dataset")
    parser.add_argument("--shard", type=int, default=0, help="shard number K (0-based)")
    parser.add_argument("--num-shards", type=int, default=1, help="number of shards N (every N-th scan from K)")
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="shard directory to write (atomically)")


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.domains.builder import build_domain_shard
    from omnilidar.domains.spec import get_domain

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    domain = get_domain(settings, args.domain)
    sidecar = build_domain_shard(domain, args.index, args.shard, args.num_shards, settings, args.seed, args.out)
    n_in = sum(s["num_points_in"] for s in sidecar["scans"])
    n_out = sum(s["num_points_out"] for s in sidecar["scans"])
    print(f"built {args.domain} shard {args.shard}/{args.num_shards}: {len(sidecar['scans'])} scans, "
          f"{n_in} -> {n_out} points -> {args.out}")
    return 0
