"""Global Alignment and Proportion (GAP) score, Yilgor et al., JBJS Am 2017;99:1661.

Pure vectorised functions over numpy arrays (angles in degrees, LDI in percent, age in years).  The thresholds
follow the score's open implementations (docs/explanation/measurement.md, "GAP"); continuous values are binned
with the half-open bins below, which equal the published 0.1-degree table on its grid and close the gaps the
table leaves (e.g. RPV in (-7.1, -7)):

    RPV: x < -15 -> 3;  -15 <= x < -7 -> 2;  -7 <= x <= 5 -> 0;  x > 5 -> 1
    RLL: x < -25 -> 3;  -25 <= x < -14 -> 2; -14 <= x <= 11 -> 0; x > 11 -> 3
    LDI: x < 40 -> 2;   40 <= x < 50 -> 1;   50 <= x <= 80 -> 0;  x > 80 -> 3
    RSA: x > 18 -> 3;   10 < x <= 18 -> 1;   -7 <= x <= 10 -> 0;  x < -7 -> 1
    Age: < 60 -> 0;  >= 60 -> 1
    Total: 0-2 proportioned (P), 3-6 moderately (MD), >= 7 severely disproportioned (SD)

LDI points 2/1/0/3 are the majority reading of the open implementations (the least certain item).
A NaN input gives NaN points, so a missing measurement is never silently scored as aligned.
"""

from __future__ import annotations

import numpy as np

#: Minimum L1-S1 lordosis (deg) for which the LDI ratio is reported; below it LDI is NaN.
LDI_MIN_LL_DEG = 1.0

CATEGORIES = ("P", "MD", "SD")


def _as_float(x) -> np.ndarray:
    return np.asarray(x, dtype=float)


def ideal_sacral_slope_deg(pi_deg):
    """PI-based ideal sacral slope, 0.59*PI + 9 (deg)."""
    return 0.59 * _as_float(pi_deg) + 9.0


def ideal_lumbar_lordosis_deg(pi_deg):
    """PI-based ideal L1-S1 lordosis, 0.62*PI + 29 (deg)."""
    return 0.62 * _as_float(pi_deg) + 29.0


def ideal_global_tilt_deg(pi_deg):
    """PI-based ideal global tilt, 0.48*PI - 15 (deg)."""
    return 0.48 * _as_float(pi_deg) - 15.0


def relative_pelvic_version_deg(ss_deg, pi_deg):
    """RPV = measured SS - ideal SS (deg); negative = retroverted."""
    return _as_float(ss_deg) - ideal_sacral_slope_deg(pi_deg)


def relative_lumbar_lordosis_deg(ll_deg, pi_deg):
    """RLL = measured L1-S1 lordosis - ideal LL (deg); negative = hypolordotic."""
    return _as_float(ll_deg) - ideal_lumbar_lordosis_deg(pi_deg)


def relative_spinopelvic_alignment_deg(gt_deg, pi_deg):
    """RSA = measured GT - ideal GT (deg); positive = forward malalignment."""
    return _as_float(gt_deg) - ideal_global_tilt_deg(pi_deg)


def lordosis_distribution_index(ll_l4s1_deg, ll_deg, min_ll_deg: float = LDI_MIN_LL_DEG):
    """LDI = 100 * LL(L4-S1) / LL(L1-S1) in percent; NaN where LL(L1-S1) <= ``min_ll_deg``.

    The ratio is meaningless (sign flips, blows up) for a straight or kyphotic lumbar spine.
    """
    ll = _as_float(ll_deg)
    l4 = _as_float(ll_l4s1_deg)
    defined = ll > min_ll_deg
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(defined, 100.0 * l4 / np.where(defined, ll, 1.0), np.nan)


def _bin(x, conditions_points) -> np.ndarray:
    x = _as_float(x)
    conds = [c(x) for c, _ in conditions_points]
    pts = [p for _, p in conditions_points]
    return np.select(conds, pts, default=np.nan)


def rpv_points(rpv_deg):
    """GAP points of the relative pelvic version (3/2/0/1; NaN for NaN)."""
    return _bin(
        rpv_deg, [(lambda x: x < -15, 3.0), (lambda x: x < -7, 2.0), (lambda x: x <= 5, 0.0), (lambda x: x > 5, 1.0)]
    )


def rll_points(rll_deg):
    """GAP points of the relative lumbar lordosis (3/2/0/3; NaN for NaN)."""
    return _bin(
        rll_deg, [(lambda x: x < -25, 3.0), (lambda x: x < -14, 2.0), (lambda x: x <= 11, 0.0), (lambda x: x > 11, 3.0)]
    )


def ldi_points(ldi_percent):
    """GAP points of the lordosis distribution index (2/1/0/3; NaN for NaN)."""
    return _bin(
        ldi_percent,
        [(lambda x: x < 40, 2.0), (lambda x: x < 50, 1.0), (lambda x: x <= 80, 0.0), (lambda x: x > 80, 3.0)],
    )


def rsa_points(rsa_deg):
    """GAP points of the relative spinopelvic alignment (3/1/0/1; NaN for NaN)."""
    return _bin(
        rsa_deg, [(lambda x: x > 18, 3.0), (lambda x: x > 10, 1.0), (lambda x: x >= -7, 0.0), (lambda x: x < -7, 1.0)]
    )


def age_points(age_years):
    """GAP age factor: 1 point at age >= 60 years, else 0 (NaN for NaN)."""
    return _bin(age_years, [(lambda x: x >= 60, 1.0), (lambda x: x < 60, 0.0)])


def gap_total(rpv_pts, rll_pts, ldi_pts, rsa_pts, age_pts=0.0):
    """Sum of the component points (NaN if any component is NaN)."""
    return _as_float(rpv_pts) + _as_float(rll_pts) + _as_float(ldi_pts) + _as_float(rsa_pts) + _as_float(age_pts)


def gap_category(total) -> np.ndarray:
    """Category of a GAP total: "P" (0-2), "MD" (3-6), "SD" (>= 7); "" where the total is NaN."""
    t = _as_float(total)
    return np.select([t <= 2, t <= 6, t > 6], ["P", "MD", "SD"], default="").astype(object)


def gap_score(
    pi_deg,
    ss_deg,
    ll_deg,
    ll_l4s1_deg,
    gt_deg,
    age_years=np.nan,
    ldi_undefined_points: float = 0.0,
    min_ll_deg: float = LDI_MIN_LL_DEG,
) -> dict[str, np.ndarray]:
    """Full GAP from the measured angles (deg) and age (years; NaN = unknown).

    ldi_undefined_points: points given to LDI where it is undefined (LL <= ``min_ll_deg``); 0 as in the open
        implementations (the hypolordosis is already scored by RLL).  Pass NaN to make GAP NaN there.
    Returns RPV, RLL, LDI, RSA, their points, ``GAP_noage`` (0-12), ``Age_pts``, ``GAP`` and ``GAP_category``.
    """
    rpv = relative_pelvic_version_deg(ss_deg, pi_deg)
    rll = relative_lumbar_lordosis_deg(ll_deg, pi_deg)
    ldi = lordosis_distribution_index(ll_l4s1_deg, ll_deg, min_ll_deg)
    rsa = relative_spinopelvic_alignment_deg(gt_deg, pi_deg)
    pts = {
        "RPV_pts": rpv_points(rpv),
        "RLL_pts": rll_points(rll),
        "LDI_pts": np.where(np.isnan(ldi), ldi_undefined_points, ldi_points(ldi)),
        "RSA_pts": rsa_points(rsa),
    }
    noage = gap_total(*pts.values())
    agep = age_points(age_years)
    total = noage + agep
    return {
        "RPV": rpv,
        "RLL": rll,
        "LDI": ldi,
        "RSA": rsa,
        **pts,
        "GAP_noage": noage,
        "Age_pts": agep,
        "GAP": total,
        "GAP_category": gap_category(total),
    }
