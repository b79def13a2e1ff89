"""Where the real LiDAR samples are: one setting for every test that reads them.

The samples stay outside the repository (their licences keep them there). Set
OMNILIDAR_REAL_DATA to their folder (relative paths are taken from the repository
root); the default is ../shared/data/real beside the repository. Without them, the
tests that read them skip with one reason and every other test runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
REAL = (ROOT / os.environ.get("OMNILIDAR_REAL_DATA", "../shared/data/real")).resolve()
REASON = f"real LiDAR samples not found at {REAL} (set OMNILIDAR_REAL_DATA)"

# For tests that read the samples: @needs_real, pytestmark = needs_real, or require_real().
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=REASON)


def require_real() -> Path:
    """The samples' folder; skips the calling test (or fixture's tests) when it is absent."""
    if not REAL.is_dir():
        pytest.skip(REASON)
    return REAL
