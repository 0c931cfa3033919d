"""Measurement against the synthetic generator's ground truth (issue: every imposed parameter recovered).

The generator knows each parameter because it placed the geometry (spinecohort.cohort.synthetic); the
measurement fits planes and spheres to landmark vertices in a frame it derives from the femoral heads and
the given vertical.  The two share no code.
"""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from spinecohort.cohort.landmarks import DISCS, disc_name
from spinecohort.cohort.synthetic import RESOLUTIONS, build_patient_mesh, draw_patient, generate_cohort
from spinecohort.measure.spinopelvic import measure

ANGLES = [
    "PI",
    "PT",
    "SS",
    "LL",
    "LL_L4S1",
    "LL_L1L5",
    "PI_minus_LL",
    "LL_minus_PI",
    "GT",
    "GT_T1",
    "T1SPI",
    "TPA",
    "TK_T1T12",
    "TK_T4T12",
    "TK_T5T12",
    "Cobb",
    "RPV",
    "RLL",
    "RSA",
]
DISTANCES = ["SVA_T1", "SVA_C7est", "FH_radius_L", "FH_radius_R", "HA_width"] + [
    f"DH_{disc_name(u, lo)}" for u, lo in DISCS
]

# Tolerances after rotation about the vertical + translation + 0.3 mm vertex noise (issue targets:
# 0.5 deg, 0.5 mm).  SVA proxies use a single rim vertex (the S1 posterosuperior corner), so 0.3 mm
# noise on that vertex is their largest error source (0.33 mm max on 42 patients).  LDI is a ratio (%).
TOL_ANGLE_DEG = 0.5
TOL_MM: dict[str, float] = {}
TOL_LDI_PCT = 1.5


@pytest.fixture(scope="module")
def cohort():
    return generate_cohort(8, seed=21, resolution="default")


def _errors(measured: pd.DataFrame, truth: pd.DataFrame) -> pd.Series:
    cols = ANGLES + DISTANCES + ["LDI"]
    return (measured[cols].reset_index(drop=True) - truth[cols].reset_index(drop=True)).abs().max()


def test_clean_cohort_is_recovered_to_round_off(cohort):
    m = measure(cohort.vertices, cohort.landmarks, age=cohort.table["age"].to_numpy())
    err = _errors(m, cohort.table)
    assert err.max() < 1e-6, err[err > 1e-6]
    assert list(m["Cobb_upper"]) == list(cohort.table["Cobb_upper"])
    assert list(m["Cobb_lower"]) == list(cohort.table["Cobb_lower"])
    # the identity PI = PT + SS holds for every measured model
    assert np.abs(m["PI"] - m["PT"] - m["SS"]).max() < 1e-6


def test_recovered_after_rotation_translation_and_noise(cohort):
    rng = np.random.default_rng(8)
    pts = []
    for v in cohort.vertices:
        rot = Rotation.from_euler("z", rng.uniform(-180, 180), degrees=True).as_matrix()
        pts.append(v @ rot.T + rng.normal(0, 50, 3) + rng.normal(0, 0.3 / np.sqrt(3), v.shape))  # 0.3 mm RMS per vertex
    m = measure(np.stack(pts), cohort.landmarks, age=cohort.table["age"].to_numpy())
    err = _errors(m, cohort.table)
    for col in ANGLES:
        assert err[col] < TOL_ANGLE_DEG, (col, err[col])
    for col in DISTANCES:
        assert err[col] < TOL_MM.get(col, 0.5), (col, err[col])
    assert err["LDI"] < TOL_LDI_PCT
    assert np.abs(m["PI"] - m["PT"] - m["SS"]).max() < 1e-6  # PI = PT + SS to 1e-6 deg, noise or not


def test_negative_pelvic_tilt_is_signed():
    p = draw_patient(np.random.default_rng(4), "P01")
    p.PT = -6.0  # anteverted pelvis: hip axis behind the S1 midpoint
    v, _, lm, truth = build_patient_mesh(p, RESOLUTIONS["coarse"], rng=np.random.default_rng(1))
    m = measure(v, lm).iloc[0]
    assert m["PT"] == pytest.approx(-6.0, abs=1e-6)
    assert m["SS"] == pytest.approx(p.PI + 6.0, abs=1e-6)
    assert m["PI"] == pytest.approx(p.PI, abs=1e-6) and truth["PT"] == -6.0
