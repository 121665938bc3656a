"""Shared test fixtures and helpers: where the repository and the real truck recordings are; a command's JSON."""
import json
from pathlib import Path

import pytest

from fuelid.cli import main

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


@pytest.fixture(autouse=True)
def no_dataset_cache(monkeypatch):
    """Commands build their data sets afresh in tests (no cache files beside shared or checked-in recordings);
    tests/ident/test_datacache.py turns the cache on where it tests it."""
    monkeypatch.setenv("FUELID_DATASET_CACHE", "0")


def run_json(capsys, *args):
    """The JSON that `fuelid ARGS --json` prints, run in-process (its exit status 0 asserted)."""
    assert main([*map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)
