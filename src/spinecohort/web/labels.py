"""What the page calls each column: a clinician's name, the unit and a one-line explanation for the hover.

Short column names (``PI``, ``TK_T4T12``) stay the keys of the table, the filters and the downloads; the
page shows :func:`label` and :func:`explain` next to them.  Definitions follow the measurement code
(``measure.spinopelvic``, ``measure.gap_score``) and its documentation.
"""

from __future__ import annotations

import re

import numpy as np

from spinecohort.web.data import unit_of

#: column -> (full name, one-sentence explanation)
PARAMETERS: dict[str, tuple[str, str]] = {
    "PI": (
        "Pelvic incidence",
        "Angle between the perpendicular to the S1 endplate at its midpoint and the line from there to the "
        "femoral-head axis; a fixed property of the pelvis (PI = PT + SS).",
    ),
    "PT": (
        "Pelvic tilt",
        "Angle between the vertical and the line from the femoral-head axis to the S1 endplate midpoint; "
        "rises as the pelvis retroverts to compensate.",
    ),
    "SS": ("Sacral slope", "Angle between the S1 upper endplate and the horizontal."),
    "LL": ("Lumbar lordosis L1–S1", "Cobb angle between the upper endplates of L1 and S1."),
    "PI_minus_LL": (
        "PI − LL mismatch",
        "Pelvic incidence minus lumbar lordosis; above about 10° the lordosis is too small for the pelvis.",
    ),
    "GT": (
        "Global tilt",
        "Angle between the lines from the S1 endplate midpoint to the C7 centre and to the femoral-head axis "
        "(GT = PT + C7 vertical tilt); grows as the trunk leans forward.",
    ),
    "TPA": (
        "T1 pelvic angle",
        "Angle between the lines from the femoral-head axis to the T1 centre and to the S1 endplate midpoint "
        "(TPA = PT + T1 spinopelvic inclination); independent of compensation by pelvic tilt.",
    ),
    "TK_T1T12": ("Thoracic kyphosis T1–T12", "Cobb angle between the upper endplate of T1 and the lower of T12."),
    "TK_T4T12": ("Thoracic kyphosis T4–T12", "Cobb angle between the upper endplate of T4 and the lower of T12."),
    "TK_T5T12": ("Thoracic kyphosis T5–T12", "Cobb angle between the upper endplate of T5 and the lower of T12."),
    "Cobb": ("Coronal Cobb angle", "Largest coronal Cobb angle between two vertebral endplates (scoliosis)."),
    "SVA_T1": (
        "Sagittal vertical axis (T1)",
        "Horizontal distance from the plumb line of the T1 centre to the posterior-superior corner of S1; "
        "positive when T1 lies in front of it.",
    ),
    "SVA_C7est": (
        "Sagittal vertical axis (C7, estimated)",
        "SVA measured from a C7 position extrapolated from the thoracic spine (the models end at T1).",
    ),
    "GAP": (
        "GAP score",
        "Global Alignment and Proportion score (Yilgor 2017), 0–13 points from relative pelvic version, "
        "relative lumbar lordosis, lordosis distribution, relative spinopelvic alignment and age.",
    ),
    "GAP_assumed_age": (
        "GAP score (age points assumed)",
        "GAP score with the age points of an assumed age: a virtual model has no age.",
    ),
    "GAP_category": (
        "GAP category",
        "Proportioned (0–2 points), moderately disproportioned (3–6) or severely disproportioned (≥ 7).",
    ),
    "min_sj_after": (
        "Minimum scaled Jacobian",
        "Worst hexahedral element shape of the FE model: 1 is a perfect cube, ≤ 0 an inverted element.",
    ),
    "invalid_after": ("Inverted elements", "Number of hexahedra with a non-positive Jacobian in the FE model."),
    "repaired": ("Mesh repaired", "Local untangling moved nodes to make every element valid."),
    "distracted": ("Discs distracted", "The disc-contact distraction moved vertebrae apart (distraction > 0 mm)."),
    "kind": ("Model", "A grid model of the virtual cohort, or a patient's personalized model."),
    "model_id": ("Model ID", "model_NNNNN for a grid model, the patient ID for a personalized model."),
}

#: GAP category code -> words, in severity order
GAP_CATEGORIES = {
    "P": "proportioned",
    "MD": "moderately disproportioned",
    "SD": "severely disproportioned",
}


def label(column: str) -> str:
    """Full name of a column, e.g. ``PI`` -> ``Pelvic incidence``, ``DH_L4-L5`` -> ``Disc height L4–L5``,
    ``w2`` -> ``Shape mode 2``; an unknown column keeps its name."""
    if column in PARAMETERS:
        return PARAMETERS[column][0]
    m = re.fullmatch(r"w(\d+)", column)
    if m:
        return f"Shape mode {m.group(1)}"
    m = re.fullmatch(r"(DHa|DHp|DH)_(\w+)-(\w+)", column)
    if m:
        where = {"DH": "", "DHa": " anterior", "DHp": " posterior"}[m.group(1)]
        return f"Disc height{where} {m.group(2)}–{m.group(3)}"
    return column


def explain(column: str) -> str:
    """One sentence for the hover of a column (what it measures and how)."""
    if column in PARAMETERS:
        return PARAMETERS[column][1]
    if re.fullmatch(r"w\d+", column):
        return (
            "Weight of this mode of the statistical shape model, in standard deviations of the training "
            "cohort (0 = the mean shape)."
        )
    if column.startswith("DH"):
        return "Height of the intervertebral disc between the two endplates (centre, anterior or posterior)."
    return ""


def label_with_unit(column: str) -> str:
    """``Pelvic incidence (deg)``; no brackets for unitless columns."""
    u = unit_of(column)
    return f"{label(column)} ({u})" if u else label(column)


def gap_words(code) -> str:
    """``MD`` -> ``moderately disproportioned``; '' for a missing category; other values unchanged."""
    if code is None or (isinstance(code, float) and not np.isfinite(code)):
        return ""
    return GAP_CATEGORIES.get(str(code), str(code))


def empty_columns(table, columns) -> list[str]:
    """Columns of ``table`` among ``columns`` without a single value (all NaN / empty): the page hides them."""
    out = []
    for c in columns:
        v = table[c]
        if v.dtype.kind in "fc":
            if not np.isfinite(v.to_numpy(float)).any():
                out.append(c)
        elif v.dtype.kind != "b" and (v.isna() | (v.fillna("").astype(str).str.strip() == "")).all():
            out.append(c)
    return out
