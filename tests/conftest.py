import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # the test processes share the cores: one BLAS/OpenMP thread each (more threads than cores spin and
    # slowed the registration fixture 5x), set before numpy loads its BLAS; the pipeline runs they start inherit it
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spinecohort.cohort.synthetic import generate_cohort
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, build_template
from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.procrustes import procrustes_align


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


@pytest.fixture(scope="session")
def test_run(tmp_path_factory):
    """The whole DAG (including the release) run once on .test/config in a fresh work dir; returns it."""
    root = Path(__file__).resolve().parents[1]
    work = tmp_path_factory.mktemp("dag")
    shutil.copytree(root / ".test" / "config", work / "config")
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(root / "Snakefile"), "--directory", str(work), "-j2"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return work
