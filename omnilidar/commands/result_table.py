"""omnilidar result-table: a result JSON as an HTML page of tables (gathered by snakemake --report)."""

from __future__ import annotations

HELP = "render a result JSON as an HTML page of tables for the workflow report"


def add_arguments(parser) -> None:
    parser.add_argument("result", help="a results/*.json file")
    parser.add_argument("--out", required=True, help="HTML page to write")


def run(args) -> int:
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.io.json_file import read_json
    from omnilidar.report.result_table import result_table_html

    result = read_json(args.result, "result JSON not found")
    if not isinstance(result, dict):
        raise InputError(args.result, f"a result is a JSON object, found {type(result).__name__}")
    write_text_atomic(args.out, result_table_html(result))
    return 0
