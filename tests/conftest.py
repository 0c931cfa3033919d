import numpy as np
import pytest

from spinecohort.hex_template import TEMPLATE_RESOLUTIONS, build_template
from spinecohort.pca import build_ssm
from spinecohort.procrustes import procrustes_align
from spinecohort.synthetic import generate_cohort


@pytest.fixture(scope="session")
def small_cohort():
    """Eight coarse synthetic patients (about 17k vertices each); built once per test session."""
    return generate_cohort(8, seed=7, resolution="coarse")


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def ssm(small_cohort):
    """The SSM of the small cohort."""
    return build_ssm(procrustes_align(small_cohort.vertices).aligned)


@pytest.fixture(scope="session")
def template(ssm, small_cohort):
    """The coarse hex template placed on the small cohort's SSM mean (not morphed)."""
    return build_template(ssm.mean, small_cohort.faces, small_cohort.landmarks, TEMPLATE_RESOLUTIONS["coarse"])
