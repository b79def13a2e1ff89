"""The ``omnilidar`` command line: one subcommand per pipeline stage.

Each module in ``omnilidar.commands`` is a subcommand. It defines ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> int | None``. Modules keep
their heavy imports inside ``run`` so that ``omnilidar --help`` stays fast.

Running a stage imports only that stage's module (the whole list is imported for
``omnilidar --help`` or an unknown stage), so a stage runs exactly the code its
code hash covers (``omnilidar.provenance.command_code_hash``).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import shlex
import sys

from omnilidar import __version__, commands
from omnilidar.allocator import keep_freed_memory
from omnilidar.errors import InputError


def _command_names() -> list[str]:
    """Subcommand names, found without importing their modules."""
    return sorted(info.name.replace("_", "-") for info in pkgutil.iter_modules(commands.__path__)
                  if not info.name.startswith("_"))


def _command_modules(only: str | None = None):
    for name in _command_names():
        if only is None or name == only:
            yield name, importlib.import_module(f"{commands.__name__}.{name.replace('-', '_')}")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``omnilidar`` parser; with ``only``, the subparser of that stage alone."""
    parser = argparse.ArgumentParser(
        prog="omnilidar",
        description="OmniLiDAR generative data augmentation pipeline. Each subcommand is one "
        "workflow stage; Snakemake calls them, and any stage can be rerun by hand with the "
        "line shown in its log.",
    )
    parser.add_argument("--version", action="version", version=f"omnilidar {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="STAGE", required=True)
    for name, module in _command_modules(only):
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else argv
    stage = next((a for a in given if not a.startswith("-")), None)
    args = build_parser(stage if stage in _command_names() else None).parse_args(argv)
    if not sys.stderr.isatty():
        # Logs start with the exact line that reruns this stage by hand.
        print("$ omnilidar " + shlex.join(sys.argv[1:] if argv is None else argv), file=sys.stderr, flush=True)
    keep_freed_memory()
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
