"""Shared test fixtures."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED_FABRICS = Path(__file__).resolve().parents[1].parent / "shared" / "fabrics"


@pytest.fixture
def shared_fabrics() -> Path:
    """The real fabric photographs in ../shared/fabrics; the test skips when they are absent."""
    if not SHARED_FABRICS.is_dir() or not any(SHARED_FABRICS.iterdir()):
        pytest.skip("../shared/fabrics is absent")
    return SHARED_FABRICS
