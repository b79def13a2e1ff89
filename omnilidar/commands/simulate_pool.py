"""omnilidar simulate-pool: a pool of real labelled scans through a domain's scene, labels carried."""

from __future__ import annotations

from omnilidar.commands._common import pool_transform_args, seed_arg

HELP = "run a pool of real labelled scans through a domain's scene (the domain builder), labels carried"
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    pool_transform_args(parser, "domain key of the domains section (fog, snow, ...)")
    seed_arg(parser)


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.domains.simulated_pool import simulate_pool
    from omnilidar.domains.spec import get_domain

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    doc = simulate_pool(get_domain(settings, args.domain), args.index, args.pool, args.seed, args.out)
    print(f"{args.domain}: {doc['num_scans']} pool scans simulated -> {args.out}/pool.json")
    return 0
