"""Anatomical label names of the reference spine, and how they map onto the cohort's part labels.

The reference (``spinecohort/data/reference/reference_spine.npz``, read with
:func:`spinecohort.anatomy.reference.load_reference`) is one triangulated surface of T1-L5, the sacrum,
both hip bones and both proximal femurs in RAS millimetres (x to the patient's right, y anterior, z up).
Every vertex carries three small integers:

``region``  index into :data:`REGIONS` (what the bone part is),
``level``   index into :data:`spinecohort.cohort.landmarks.LEVELS` (T1..L5) for a vertebra vertex, else -1,
``side``    -1 patient left (x < 0), +1 patient right, 0 midline or unpaired.

A vertebra's vertices are ``level == i``; its pedicles are ``(level == i) & (region == REGIONS.index(
"pedicle_left"))``, and so on.  Morphometry (body width/depth/height, pedicle width/height, spinous process
length, facet orientation) is measured on these regions.

The endplate sets (patch and rim of every superior and inferior endplate, ``S1`` included) and the
femoral-head sphere patches are stored as the :class:`spinecohort.cohort.landmarks.Landmarks` of the
reference; ligament insertion sites as vertex sets named ``site_<LIGAMENT>_<where>`` (:data:`LIGAMENT_SITES`).
The sacrum carries the lower side of the L5-S1 joint (:mod:`spinecohort.anatomy.sacrum`): the sets
``facet_surface_sup_<side>``, ``site_CL_sup_<side>``, ``site_LF_sup_<side>``, ``site_ISL_sup`` and ``site_SSL``
have a key ``"S1"``, and its anchors are the one-vertex sets ``anchor_<name>`` (key ``"S1"``).
"""

from __future__ import annotations

import numpy as np

from spinecohort.cohort.landmarks import LEVELS

#: Bone regions, in label order.  Paired structures carry the side in the name (patient left / right).
REGIONS: tuple[str, ...] = (
    "body",  # vertebral body: cortical wall and both endplates
    "pedicle_left",
    "pedicle_right",
    "lamina",  # both laminae (the neural arch roof between pedicles and the spinous process)
    "spinous",  # spinous process
    "transverse_left",
    "transverse_right",
    "facet_sup_left",  # superior articular process, left (its articular surface is a facet set)
    "facet_sup_right",
    "facet_inf_left",  # inferior articular process, left
    "facet_inf_right",
    "sacrum",  # sacrum below and behind the S1 plate (alae, sacral canal, S1 superior facets included)
    "s1_plate",  # the S1 superior endplate region of the sacrum
    "ilium",  # hip bone: ilium with the acetabulum and ischium
    "pubis",  # hip bone: pubic body and rami around the symphysis
    "femoral_head",  # femoral head, neck and the proximal shaft kept to fit the head
)

#: Regions of a vertebra (T1..L5).
VERTEBRA_REGIONS: tuple[str, ...] = REGIONS[:11]

#: Ligament insertion sites stored on the reference, ``site_<name>`` -> where it is.  Each site is a
#: vertex set per level (key ``"<LIGAMENT>_<where>"``, value: level -> vertex indices).
LIGAMENT_SITES: dict[str, str] = {
    "ALL_sup": "anterior longitudinal ligament: anterior midline band of the body next to the superior endplate",
    "ALL_inf": "anterior longitudinal ligament: anterior midline band of the body next to the inferior endplate",
    "PLL_sup": "posterior longitudinal ligament: posterior midline band of the body next to the superior endplate",
    "PLL_inf": "posterior longitudinal ligament: posterior midline band of the body next to the inferior endplate",
    "LF_sup_left": "ligamentum flavum: cranial edge of the left lamina (inner side)",
    "LF_sup_right": "ligamentum flavum: cranial edge of the right lamina (inner side)",
    "LF_inf_left": "ligamentum flavum: caudal edge of the left lamina (inner side)",
    "LF_inf_right": "ligamentum flavum: caudal edge of the right lamina (inner side)",
    "ISL_sup": "interspinous ligament: cranial edge of the spinous process",
    "ISL_inf": "interspinous ligament: caudal edge of the spinous process",
    "SSL": "supraspinous ligament: the tip of the spinous process",
    "ITL_left": "intertransverse ligament: tip of the left transverse process",
    "ITL_right": "intertransverse ligament: tip of the right transverse process",
    "CL_sup_left": "capsular ligament: rim of the left superior facet articular surface",
    "CL_sup_right": "capsular ligament: rim of the right superior facet articular surface",
    "CL_inf_left": "capsular ligament: rim of the left inferior facet articular surface",
    "CL_inf_right": "capsular ligament: rim of the right inferior facet articular surface",
}

#: Facet articular surfaces (vertex sets per level, left/right, superior/inferior): ``facet_surface_<...>``.
FACET_SURFACES: tuple[str, ...] = ("sup_left", "sup_right", "inf_left", "inf_right")


def region_id(name: str) -> int:
    """Label of a region name; a clear error for an unknown one."""
    try:
        return REGIONS.index(name)
    except ValueError:
        raise ValueError(f"unknown anatomical region {name!r}; the regions are {', '.join(REGIONS)}") from None


def level_id(level: str) -> int:
    """Index (0 = T1 ... 16 = L5) of a vertebral level name."""
    try:
        return LEVELS.index(level)
    except ValueError:
        raise ValueError(f"unknown vertebral level {level!r}; the levels are {', '.join(LEVELS)}") from None


def cohort_part_names() -> tuple[str, ...]:
    """The part names of the cohort's :class:`Landmarks` (what the SSM, hex template and contact code read):
    ``body_<lv>`` and ``posterior_<lv>`` for every level, ``sacrum``, ``pelvis``, ``femoral_head_L/R``."""
    return (
        tuple(f"body_{lv}" for lv in LEVELS)
        + tuple(f"posterior_{lv}" for lv in LEVELS)
        + ("sacrum", "pelvis", "femoral_head_L", "femoral_head_R")
    )


def cohort_part(region: np.ndarray, level: np.ndarray, side: np.ndarray) -> np.ndarray:
    """(N,) int16 cohort part label (index into :func:`cohort_part_names`) of every reference vertex.

    body -> ``body_<lv>``; the other vertebral regions -> ``posterior_<lv>``; sacrum and S1 plate -> ``sacrum``;
    ilium and pubis -> ``pelvis``; femoral head -> ``femoral_head_L`` (side -1) or ``_R`` (side +1).
    """
    region, level, side = (np.asarray(a) for a in (region, level, side))
    nl = len(LEVELS)
    out = np.full(region.shape, -1, dtype=np.int16)
    vert = level >= 0
    out[vert & (region == 0)] = level[vert & (region == 0)]
    post = vert & (region > 0) & (region < len(VERTEBRA_REGIONS))
    out[post] = nl + level[post]
    out[np.isin(region, [region_id("sacrum"), region_id("s1_plate")])] = 2 * nl
    out[np.isin(region, [region_id("ilium"), region_id("pubis")])] = 2 * nl + 1
    head = region == region_id("femoral_head")
    out[head & (side < 0)] = 2 * nl + 2
    out[head & (side > 0)] = 2 * nl + 3
    if np.any(out < 0):
        bad = np.flatnonzero(out < 0)[:5]
        raise ValueError(f"vertices {bad.tolist()} have no cohort part (region/level/side inconsistent)")
    return out
