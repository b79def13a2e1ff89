"""The ``omnilidar`` command line: one subcommand per pipeline stage.

Each module in ``omnilidar.commands`` is a subcommand. It defines ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> int | None``. Modules keep
their heavy imports inside ``run`` so that ``omnilidar --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import shlex
import sys

from omnilidar import __version__, commands
from omnilidar.errors import InputError


def _command_modules():
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield info.name.replace("_", "-"), importlib.import_module(f"{commands.__name__}.{info.name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="omnilidar",
        description="OmniLiDAR generative data augmentation pipeline. Each subcommand is one "
        "workflow stage; Snakemake calls them, and any stage can be rerun by hand with the "
        "line shown in its log.",
    )
    parser.add_argument("--version", action="version", version=f"omnilidar {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="STAGE", required=True)
    for name, module in _command_modules():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not sys.stderr.isatty():
        # Logs start with the exact line that reruns this stage by hand.
        print("$ omnilidar " + shlex.join(sys.argv[1:] if argv is None else argv), file=sys.stderr, flush=True)
    try:
        code = args._run(args)
    except InputError as err:
        print(f"omnilidar {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"omnilidar {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
