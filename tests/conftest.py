import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # the test processes share the cores: one BLAS/OpenMP thread each (more threads than cores spin and
    # slowed the registration fixture 5x), set before numpy loads its BLAS; the pipeline runs they start inherit it
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import shutil
import subprocess
import sys
from dataclasses import replace
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


@pytest.fixture(scope="session")
def real_template():
    """The coarse hex template on the labeled reference (the real cohort's shape and numbering), with the facet
    surfaces, the labeled pedicles and ALL / PLL / LF / CL bundles of the default config."""
    from spinecohort.anatomy.reference import load_reference
    from spinecohort.cohort.real import first_use_reference

    ref = first_use_reference(load_reference())
    res = replace(TEMPLATE_RESOLUTIONS["coarse"], cep_diameter_fraction=0.7)
    return build_template(ref.vertices, ref.faces, ref.landmarks, res, fibres={"ALL": 3, "PLL": 3, "LF": 3, "CL": 4})
