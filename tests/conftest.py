import numpy as np
import pytest

import lensforge as lf


@pytest.fixture(scope="session")
def bench():
    return lf.Bench.default()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
