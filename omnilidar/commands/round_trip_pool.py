"""omnilidar round-trip-pool: a pool of real labelled scans through a domain's range image and back."""

from __future__ import annotations

from omnilidar.commands._common import pool_transform_args

HELP = ("send a pool of real labelled scans through a domain's range image and back, labels carried "
        "(a perfect generator's scans at that image size)")
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    pool_transform_args(parser, "domain key of the domains section (its sensor and range_image geometry)")


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.domains.simulated_pool import round_trip_pool
    from omnilidar.domains.spec import get_domain

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    doc = round_trip_pool(get_domain(settings, args.domain), settings, args.index, args.pool, args.out)
    ri = doc["round_trip"]["range_image"]
    print(f"{args.domain}: {doc['num_scans']} pool scans through {ri['height']} x {ri['width']} range images "
          f"and back -> {args.out}/pool.json")
    return 0
