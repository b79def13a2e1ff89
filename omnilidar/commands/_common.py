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
