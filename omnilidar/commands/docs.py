"""omnilidar docs: write README's and docs' result blocks from the result JSON files."""

from __future__ import annotations

HELP = "rewrite the results blocks of README.md and docs/*.md from result JSON files (--check: compare only)"


def add_arguments(parser) -> None:
    parser.add_argument("pages", nargs="*", help="pages holding results blocks (default README.md and docs/*.md)")
    parser.add_argument("--results", default="docs/results",
                        help="folder of the result JSON files the pages quote (default docs/results, the "
                             "measured results kept with the repository; results/ for a fresh run)")
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 when a page disagrees")


def run(args) -> int:
    import sys
    from pathlib import Path

    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.report.readme import render_page

    stale = []
    args.pages = args.pages or ["README.md", *map(str, sorted(Path("docs").glob("*.md")))]
    for page in args.pages:
        path = Path(page)
        if not path.is_file():
            raise InputError(path, "page not found")
        text = path.read_text()
        new = render_page(text, Path(args.results), path)
        if new != text:
            stale.append(page)
            if not args.check:
                write_text_atomic(path, new)
    if args.check and stale:
        print(f"{', '.join(stale)} disagree with the results in {args.results}: run omnilidar docs --results "
              f"{args.results}", file=sys.stderr)
        return 1
    print(("checked " if args.check else "wrote ") + ", ".join(args.pages) + f" from {args.results}")
    return 0
