"""Any result JSON as an HTML page of tables, for ``snakemake --report``.

Results differ in shape, so the page follows the JSON: the envelope (experiment, data source,
device, seeds, hashes) first, then one table per section. A mapping whose values are mappings
of numbers becomes a table with one row per key and one column per inner key (deeper levels
joined with "/"); a list of such mappings becomes one row per item; a mapping of numbers or
text becomes a two-column table; whatever is nested deeper gets its own heading.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Mapping

ENVELOPE = ("experiment", "data_source", "device", "seeds", "config_hash", "code_hash", "versions")
STYLE = ("body{font-family:sans-serif;font-size:13px} table{border-collapse:collapse;margin:6px 0 14px}"
         "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right} th{background:#f2f2f2}"
         "td:first-child,th:first-child{text-align:left}")


def format_value(value) -> str:
    """Numbers with four significant digits, lists of numbers inline, the rest as JSON."""
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, str):
        return value
    if isinstance(value, list) and len(value) <= 12 and all(_is_scalar(v) for v in value):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return json.dumps(value, sort_keys=True, default=str)


def _is_scalar(value) -> bool:
    return value is None or isinstance(value, (bool, int, float, str))


def _flat_row(mapping: Mapping, prefix: str = "", depth: int = 1) -> dict | None:
    """Scalar leaves of a mapping, keys joined with "/" up to ``depth`` levels below; None when
    something deeper (or a long list) is left."""
    row = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if _is_scalar(value) or (isinstance(value, list) and len(value) <= 12 and all(map(_is_scalar, value))):
            row[name] = value
        elif isinstance(value, Mapping) and depth > 0:
            inner = _flat_row(value, f"{name}/", depth - 1)
            if inner is None:
                return None
            row.update(inner)
        else:
            return None
    return row


def _table(rows: list[tuple[str, dict]], first: str) -> str:
    columns: list[str] = []
    for _, row in rows:
        columns += [c for c in row if c not in columns]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in [first, *columns])
    body = "".join(
        "<tr>" + f"<td>{html.escape(str(name))}</td>"
        + "".join(f"<td>{html.escape(format_value(row[c])) if c in row else ''}</td>" for c in columns) + "</tr>"
        for name, row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _section(title: str, value, level: int) -> str:
    heading = f"<h{min(level, 6)}>{html.escape(title)}</h{min(level, 6)}>"
    if _is_scalar(value) or isinstance(value, list) and all(map(_is_scalar, value)):
        return f"<p><b>{html.escape(title)}</b>: {html.escape(format_value(value))}</p>"
    if isinstance(value, Mapping):
        if all(_is_scalar(v) for v in value.values()):
            return heading + _table([(k, {"value": v}) for k, v in value.items()], "key")
        rows = [(k, _flat_row(v)) if isinstance(v, Mapping) else (k, None) for k, v in value.items()]
        if rows and all(row is not None for _, row in rows):
            return heading + _table(rows, "")
        return heading + "".join(_section(str(k), v, level + 1) for k, v in value.items())
    if isinstance(value, list) and all(isinstance(v, Mapping) for v in value):
        rows = [(str(i), _flat_row(v)) for i, v in enumerate(value)]
        if all(row is not None for _, row in rows):
            return heading + _table(rows, "#")
        return heading + "".join(_section(f"{title}[{i}]", v, level + 1) for i, v in enumerate(value))
    return heading + f"<pre>{html.escape(json.dumps(value, indent=1, default=str))}</pre>"


def result_table_html(result: Mapping) -> str:
    """The HTML page of one result: its envelope, then every other section as tables."""
    title = str(result.get("experiment", "result"))
    envelope = {k: result[k] for k in ENVELOPE if k in result}
    parts = [f"<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>"]
    if envelope:
        parts.append(_table([(k, {"value": v}) for k, v in envelope.items()], "provenance"))
    parts += [_section(str(k), v, 2) for k, v in result.items() if k not in ENVELOPE]
    parts.append("</body></html>")
    return "".join(parts)
