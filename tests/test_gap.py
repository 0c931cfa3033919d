"""GAP score: bin edges of spinopelvic.md §4.3 and the worked examples of §4.4."""

from __future__ import annotations

import numpy as np
import pytest

from spinecohort.measure import gap_score as gap

EPS = 0.01  # deg / percent either side of an edge


@pytest.mark.parametrize(
    "func, cases",
    [
        # (value, points): edges of the half-open bins, at and EPS either side
        (gap.rpv_points, [(-15 - EPS, 3), (-15, 2), (-7 - EPS, 2), (-7.1, 2), (-7, 0), (5, 0), (5 + EPS, 1)]),
        (gap.rll_points, [(-25 - EPS, 3), (-25, 2), (-14 - EPS, 2), (-14.1, 2), (-14, 0), (11, 0), (11 + EPS, 3)]),
        (gap.ldi_points, [(40 - EPS, 2), (40, 1), (49, 1), (50 - EPS, 1), (50, 0), (80, 0), (80 + EPS, 3)]),
        (gap.rsa_points, [(18 + EPS, 3), (18, 1), (10.1, 1), (10 + EPS, 1), (10, 0), (-7, 0), (-7 - EPS, 1)]),
        (gap.age_points, [(59.9, 0), (60, 1), (75, 1)]),
    ],
)
def test_bin_edges(func, cases):
    values, expected = np.array(cases, dtype=float).T
    np.testing.assert_array_equal(func(values), expected)
    assert np.isnan(func(np.nan))


def test_ideal_values():
    # open JS test suite: gapIdeals(50) = {idealSS: 38.5, idealLL: 60, idealGT: 9}
    assert gap.ideal_sacral_slope_deg(50) == pytest.approx(38.5)
    assert gap.ideal_lumbar_lordosis_deg(50) == pytest.approx(60.0)
    assert gap.ideal_global_tilt_deg(50) == pytest.approx(9.0)


def test_categories():
    np.testing.assert_array_equal(gap.gap_category([0, 2, 3, 6, 7, 13, np.nan]), ["P", "P", "MD", "MD", "SD", "SD", ""])


# §4.4 worked examples: PI, SS, LL, L4-S1, GT, age -> RPV, RLL, LDI, RSA, points (RPV, RLL, LDI, RSA, age), GAP
EXAMPLES = {
    "A ideal": ((50, 38.5, 60, 39, 9, 45), (0, 0, 65.0, 0), (0, 0, 0, 0, 0), 0, "P"),
    "B ASD": ((60, 30, 30, 20, 35, 65), (-14.4, -36.2, 66.667, 21.2), (2, 3, 0, 3, 1), 9, "SD"),
    "C distal-heavy": ((45, 35, 50, 42, 5, 55), (-0.55, -6.9, 84.0, -1.6), (0, 0, 3, 0, 0), 3, "MD"),
    # open-source test case (expected "rpv 0, rll 0, ldi 2, rsa 0, af 0, total 2"); RLL 0.05 from the edge
    "D open-source": ((50.4, 35, 46.3, 18.3, 14.8, 58), (-3.736, -13.948, 39.525, 5.608), (0, 0, 2, 0, 0), 2, "P"),
}


@pytest.mark.parametrize("name", EXAMPLES)
def test_worked_examples(name):
    inputs, rel, pts, total, cat = EXAMPLES[name]
    g = gap.gap_score(*inputs)
    np.testing.assert_allclose([g["RPV"], g["RLL"], g["LDI"], g["RSA"]], rel, atol=1e-3)
    assert [float(g[k]) for k in ("RPV_pts", "RLL_pts", "LDI_pts", "RSA_pts", "Age_pts")] == list(pts)
    assert g["GAP"] == total and g["GAP_noage"] == total - pts[4] and g["GAP_category"] == cat


def test_vectorised_over_arrays():
    cols = np.array([EXAMPLES[k][0] for k in EXAMPLES], dtype=float).T
    g = gap.gap_score(*cols)
    np.testing.assert_array_equal(g["GAP"], [0, 9, 3, 2])
    assert list(g["GAP_category"]) == ["P", "SD", "MD", "P"]


def test_ldi_undefined_and_unknown_age():
    # LL = 0.5 deg <= 1 deg: LDI NaN; scored 0 by default, NaN on request; unknown age -> GAP NaN
    g = gap.gap_score(50, 38.5, 0.5, 10, 9)
    assert np.isnan(g["LDI"]) and g["LDI_pts"] == 0 and np.isnan(g["GAP"]) and g["GAP_category"] == ""
    assert g["GAP_noage"] == 3  # RLL = 0.5 - 60 = -59.5 -> 3
    assert np.isnan(gap.gap_score(50, 38.5, 0.5, 10, 9, 70, ldi_undefined_points=np.nan)["GAP"])
    assert gap.lordosis_distribution_index(30, 60) == pytest.approx(50.0)
