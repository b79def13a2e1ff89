"""Reading a JSON file another stage wrote, with one clear error for bad input."""

from __future__ import annotations

import json
from pathlib import Path

from omnilidar.errors import InputError


def read_json(path: str | Path, missing: str):
    """The parsed document at ``path``. InputError(path, ``missing``) when there is no such
    file; InputError naming the parse error when it is not valid JSON."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, missing)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(path, f"invalid JSON: {err}") from None
