"""The warning a GDA result gives when its fixed labeler is weaker than a student it labels for."""

from __future__ import annotations

import sys


def warn_about_labeler(check: dict) -> None:
    """Print a labeler check's warning on the terminal (stderr), if any."""
    if check.get("warning"):
        print(f"WARNING: {check['warning']}", file=sys.stderr, flush=True)
