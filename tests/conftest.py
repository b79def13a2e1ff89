"""Shared test fixtures: paths of the project and of the real LiDAR samples."""

from __future__ import annotations

from pathlib import Path

import pytest

from real_samples import ROOT, require_real


@pytest.fixture(scope="session")
def project_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The real LiDAR samples (OMNILIDAR_REAL_DATA); skips the test when they are absent."""
    return require_real()


@pytest.fixture(autouse=True)
def _grad_mode_is_not_left_switched_off():
    """Stages run in-process in tests: none may leave autograd switched off globally."""
    yield
    import sys

    torch = sys.modules.get("torch")
    if torch is not None:
        assert torch.is_grad_enabled(), "a stage left torch.set_grad_enabled(False) behind"
