"""Short simulated trips shared by the simulator tests (each simulated once per session); the VECTO engine sets of
../shared/engines."""
import functools
from pathlib import Path

import pytest

from fuelid.sim.trip import TripConfig, simulate


@functools.lru_cache(maxsize=None)
def _trip(**kwargs):
    return simulate(TripConfig(**kwargs))


@pytest.fixture(scope="session")
def trip():
    """trip(**TripConfig fields) -> simulated Trip, cached across tests."""
    return lambda **kwargs: _trip(**kwargs)


SHARED_ENGINES = Path(__file__).resolve().parents[2].parent / "shared" / "engines"
"""The VECTO engine sets beside the repository (../shared/engines), one folder each."""


def shared_engine_files() -> list:
    """Every .veng in ../shared/engines/*/ (none when the folder is absent: the tests using them skip)."""
    return sorted(SHARED_ENGINES.glob("*/*.veng"))


@pytest.fixture(params=[p.parent.name for p in shared_engine_files()] or ["absent"])
def shared_engine(request):
    """Path of one engine set's .veng in ../shared/engines (the test runs once per set), skipping the test when
    ../shared is absent."""
    if request.param == "absent":
        pytest.skip(f"VECTO engine sets not available ({SHARED_ENGINES})")
    return next(SHARED_ENGINES.glob(f"{request.param}/*.veng"))
