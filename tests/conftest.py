"""Shared test fixtures: where the repository and the real truck recordings are."""
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
REAL_LOGS = REPO.parent / "shared" / "real_logs"


@pytest.fixture
def real_log():
    """Path to a file in ../shared/real_logs/, skipping the test when the folder is absent."""

    def path(name: str) -> Path:
        p = REAL_LOGS / name
        if not p.exists():
            pytest.skip(f"real truck recordings not available ({p})")
        return p

    return path
