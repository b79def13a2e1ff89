"""``omnilidar synthesize``: write one shard of the synthetic (embedded default) datasets."""

from __future__ import annotations

import argparse

from omnilidar.commands._common import seed_arg, settings_arg

HELP = "generate one shard (sequence, platform or split) of a synthetic dataset in its real on-disk layout"
DATA_FILES = ("workflow/schemas/synthetic.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", choices=["semantickitti", "kitti360", "pi3det", "nuscenes"],
                        help="which dataset layout to write")
    parser.add_argument("--shard", required=True,
                        help='semantickitti: sequence "00".."21"; kitti360: sequence number; '
                             "pi3det: vehicle|drone|quadruped; nuscenes: train|val")
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--out", required=True, help="shard directory to create (replaced atomically)")


def run(args: argparse.Namespace) -> int:
    import json
    import time

    from omnilidar.config import validate
    from omnilidar.data.synthetic.export import write_shard

    settings = validate(dict(args.settings), "synthetic.schema.yaml", source="--settings (synthetic section)")
    start = time.perf_counter()
    summary = write_shard(args.dataset, args.shard, settings, args.seed, args.out)
    summary["seconds"] = round(time.perf_counter() - start, 3)
    print(json.dumps(summary))
    return 0
