import numpy as np
import pytest

#: One seed for every random generator in the tests.
TEST_SEED = 20261121


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(TEST_SEED)


@pytest.fixture(scope="session")
def nominal_log():
    """60 frames at 1 fps, ~1000 m above 300 m-relief fractal terrain, 30 m DTM."""
    from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight

    return simulate_flight(SimulationSettings(frames=60, altitude_m=1000.0, relief_m=300.0, seed=1))
