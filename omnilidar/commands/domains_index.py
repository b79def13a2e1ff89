"""omnilidar domains-index: list every built domain's shards for the generator."""

from __future__ import annotations

from omnilidar.commands._common import settings_arg

HELP = "write the domains index (name -> id and shard directories) the generator trains on"
DATA_FILES = ("workflow/schemas/domains.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    parser.add_argument("--out", required=True, help="domains index JSON to write")
    parser.add_argument("shards", nargs="+", help="shard directories written by build-domain")


def run(args) -> int:
    import json

    from omnilidar.config import validate
    from omnilidar.domains.index import domains_index
    from omnilidar.io.atomic import write_text_atomic

    settings = validate(dict(args.settings), "domains.schema.yaml", source="--settings")
    index = domains_index(settings, args.shards, args.out)
    write_text_atomic(args.out, json.dumps(index, indent=1))
    summary = ", ".join(f"{k} ({v['num_scans']} scans)" for k, v in index["domains"].items())
    print(f"indexed {len(index['domains'])} domains: {summary} -> {args.out}")
    return 0
