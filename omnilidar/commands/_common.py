"""Argument helpers shared by stage commands."""

from __future__ import annotations

import argparse
import json


def settings_arg(parser: argparse.ArgumentParser) -> None:
    """``--settings JSON``: the stage's whole (validated) config section."""
    parser.add_argument(
        "--settings",
        type=json.loads,
        default={},
        help="the stage's config section as a JSON object (Snakemake passes it)",
    )


def seed_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="root random seed")


def segment_arg(parser: argparse.ArgumentParser) -> None:
    """``--segment K/N``: train only the K-th of N parts of the run (a segment job of a chain)."""
    from omnilidar.checkpoints import parse_segment

    parser.add_argument("--segment", type=parse_segment, default=None, metavar="K/N",
                        help="train only the K-th of N equal parts of the run, leave the resumable state in "
                             "--work-dir and write a segment record (JSON) to --out; the job without it "
                             "resumes the last part and writes the weights")


def report_outputs_arg(parser: argparse.ArgumentParser, markdown: bool = True) -> None:
    """``--out`` (results JSON), ``--markdown`` (table) and ``--figure`` (PNG) of a results target."""
    parser.add_argument("--out", required=True, help="results JSON")
    if markdown:
        parser.add_argument("--markdown", required=True, help="markdown table")
    parser.add_argument("--figure", required=True, help="figure (PNG)")


def data_source_arg(parser: argparse.ArgumentParser) -> None:
    """``--data-source JSON``: every dataset the result used, real or synthetic (omnilidar.data_source)."""
    from omnilidar.data_source import parse

    parser.add_argument("--data-source", type=parse, required=True,
                        help='{dataset: {"root": path, "kind": "real" | "synthetic"}} (Snakemake passes it)')


def pool_transform_args(parser: argparse.ArgumentParser, domain_help: str) -> None:
    """DOMAIN, --index, --pool, --settings and --out of a command that transforms a pool of real
    labelled scans (simulate-pool, round-trip-pool)."""
    parser.add_argument("domain", help=domain_help)
    parser.add_argument("--index", required=True, help="dataset index JSON the pool's scans come from")
    parser.add_argument("--pool", required=True, help="pool of real scans (make-subset --exclude)")
    settings_arg(parser)
    parser.add_argument("--out", required=True, help="folder to write (atomically): velodyne/, labels/, pool.json")


def threads_arg(parser: argparse.ArgumentParser) -> None:
    """``--threads``: torch's CPU threads (omnilidar.devices.set_threads); the workflow passes the
    cores Snakemake gives the job."""
    parser.add_argument("--threads", type=int, default=1, help="CPU threads for torch (default: 1)")
