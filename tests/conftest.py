"""Shared test fixtures: paths of the project and of the real LiDAR samples."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"


@pytest.fixture(scope="session")
def project_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def real_data() -> Path:
    if not REAL.is_dir():
        pytest.fail(f"real LiDAR samples not found at {REAL} (see README: Tests)")
    return REAL


@pytest.fixture(autouse=True)
def _grad_mode_is_not_left_switched_off():
    """Stages run in-process in tests: none may leave autograd switched off globally."""
    yield
    import sys

    torch = sys.modules.get("torch")
    if torch is not None:
        assert torch.is_grad_enabled(), "a stage left torch.set_grad_enabled(False) behind"
