import numpy as np
import pytest

#: One seed for every random generator in the tests.
TEST_SEED = 20261121


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(TEST_SEED)
