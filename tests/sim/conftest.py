"""Short simulated trips shared by the simulator tests (each simulated once per session)."""
import functools

import pytest

from fuelid.sim.trip import TripConfig, simulate


@functools.lru_cache(maxsize=None)
def _trip(**kwargs):
    return simulate(TripConfig(**kwargs))


@pytest.fixture(scope="session")
def trip():
    """trip(**TripConfig fields) -> simulated Trip, cached across tests."""
    return lambda **kwargs: _trip(**kwargs)
