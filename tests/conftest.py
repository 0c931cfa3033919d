import numpy as np
import pytest

from spinecohort.synthetic import generate_cohort


@pytest.fixture(scope="session")
def small_cohort():
    """Eight coarse synthetic patients (about 17k vertices each); built once per test session."""
    return generate_cohort(8, seed=7, resolution="coarse")


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(12345)
