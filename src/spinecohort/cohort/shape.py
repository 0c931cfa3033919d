"""Per-patient shape of the real-bone column: disc heights, and vertebral body heights and wedging.

Every vertebra of the reference keeps its posterior arch rigid: the facets hinge the column
(:func:`spinecohort.cohort.real.pose_column`), so the arch fixes the distance between the joint pivots of a
segment, i.e. body height plus disc height.  The body is deformed along its own axis instead: its superior and
inferior endplates (rim band and whole concave plate) move as rigid plates (a lift along the vertebra's
mid-axis and a turn about the medio-lateral axis through the plate's centre), the body between them follows
by a smoothstep in the axial coordinate, and the motion fades to zero along the pedicles by the ratio of the
distances to the endplates and to the posterior elements (:func:`body_map`).  A disc drawn
thinner than the reference's therefore makes its two neighbouring bodies taller by half the difference each
(the L5-S1 difference goes to L5, the sacrum keeps its shape); the body wedge varies on its own.

Drawn per patient (:func:`draw_shape`), independently per level, each a normal clipped at ±``CLIP_SD`` SD:

* the central disc height (rim plane to rim plane, as ``DH_*`` is measured), ``DISC_HEIGHT_MEAN_MM`` ±
  ``DISC_HEIGHT_SD_MM``;
* the change of the body wedge, ``WEDGE_SD_DEG``.

The true endplate planes are the reference planes carried by the imposed rigid plate motions
(:func:`shaped_frames`); no fit of the deformed mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spinecohort.cohort.landmarks import LEVELS

#: Central disc heights (mm) T1-T2 ... L5-S1, healthy adults.  Thoracic: Kunkel ME, Herkommer A, Reinehr M,
#: Böckers TM, Wilke HJ. Morphometric analysis of the relationships between intervertebral disc and vertebral
#: body heights: an anatomical and radiographic study of the human thoracic spine. J Anat 2011;219(3):375-387,
#: direct measurement of 30 donors: anterior and posterior disc heights from 4.5 mm (upper) to 7.2 mm (lower
#: thoracic), the mid-disc height (with the endplate concavities) about 23 % more; the per-level table could
#: not be read here, so T1-T2 ... T11-T12 interpolate 4.5 to 7.2 mm linearly.  L1-L2 ... L5-S1: Twomey L,
#: Taylor J. Age changes in lumbar intervertebral discs. Acta Orthop Scand 1985;56(6):496-499, men aged 20-35
#: (mid-sagittal area over depth; transcribed in github.com/Gregory-Schwing-MD-PhD/CTSpinoPelvic1K
#: morphometrics/make_reference_table.py, commit 21d65b7).  T12-L1: midway between T11-T12 and L1-L2.
DISC_HEIGHT_MEAN_MM = np.concatenate([np.linspace(4.5, 7.2, 11), [8.2, 9.2, 9.8, 10.3, 11.3, 10.6]])
#: SD (mm) of the disc heights.  Thoracic: 1.0 mm, Fletcher JGR et al. CT morphometry of adult thoracic
#: intervertebral discs. Eur Spine J 2015;24(10):2321-2329 (128 adults: posterior height SD 0.90 mm in men,
#: anterior 0.7-1.4 mm by level).  Lumbar: Twomey and Taylor 1985 (above); T12-L1 between.
DISC_HEIGHT_SD_MM = np.concatenate([np.full(11, 1.0), [1.0, 1.0, 1.2, 1.0, 1.3, 1.6]])
#: SD (deg) of the change of a body's wedge angle.  1.5 deg turns the anterior height against the posterior
#: one by about 0.8 mm over a 30 mm deep endplate; with the patient's scale (SD 4 %) and the disc-coupled
#: plate lifts the body heights vary by 1-3 mm, as the SDs of Kunkel et al. 2011 (T12:
#: anterior 1.96, posterior 1.94 mm) and Busscher I et al. Eur Spine J 2010;19(7):1104-1114 (T12-L5: anterior
#: 1.4-2.8, posterior 0.9-3.8 mm) report; the sum over T4-T12 (SD 4.5 deg) stays well inside the kyphosis SD.
WEDGE_SD_DEG = 1.5
#: range (reference mm) of the inferior-plate lift per vertebra T1 ... L5.  Down: half a millimetre inside the
#: largest lowering that, with a wedge change of ±2.5 SD, leaves the vertebra free of self-intersections
#: (scanned in 0.5 mm steps to 10 mm; ``tests/test_real_shape.py`` checks the ends): the warped T1, T2 and T9
#: have their laminae and inferior articular processes within 3.4-6 mm of the inferior plate, so a plate
#: lowered further folds the body into them.  Up: a body is shortened by at most 6 mm (about a fifth of a
#: lumbar body; nothing folds up to 8 mm, T1 to 5.5 mm).  A disc that would need more stays off its drawn height.
LIFT_MIN_MM = np.array([-2.0, -3.0] + [-8.0] * 6 + [-5.0] + [-8.0] * 8)
LIFT_MAX_MM = np.array([5.0] + [6.0] * 16)
#: regions that follow the body: the pedicles bridge it to the rigid arch (their labels run down the posterior
#: wall to within 2 mm of both endplates, so a rigid pedicle would be torn by an endplate lift)
DEFORMABLE = ("body", "pedicle_left", "pedicle_right")
#: draws are clipped at this many SDs (the SD of a normal clipped at 2.5 SD is 0.97 of the unclipped one)
CLIP_SD = 2.5


@dataclass(frozen=True)
class BodyMap:
    """Patient-independent part of the body deformation, one entry per vertebra T1..L5 (reference mm)."""

    idx: tuple  # vertex indices of the vertebra
    w_sup: tuple  # (n_i,) weight of the superior plate motion per vertex (1 on the plate, 0 on the arch)
    w_inf: tuple
    axis: np.ndarray  # (17, 3) unit mid-axis (mean of the two endplate normals)
    lateral: np.ndarray  # (17, 3) unit medio-lateral axis of the mid-frame


@dataclass
class Shape:
    """One patient's plate motions: lifts (reference mm, + cranial along the mid-axis) and wedge changes."""

    lift_sup: np.ndarray  # (17,)
    lift_inf: np.ndarray  # (17,)
    wedge_deg: np.ndarray  # (17,) + lengthens the anterior body height against the posterior one

    @classmethod
    def neutral(cls) -> Shape:
        return cls(np.zeros(len(LEVELS)), np.zeros(len(LEVELS)), np.zeros(len(LEVELS)))


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def body_map(ref, fr) -> BodyMap:
    """Weights of the plate motions over every vertebra of the reference.

    Axial blend: 1 for the superior plate at and above the lowest vertex of its plate (rim band and concave
    plate), 0 at and below the highest vertex of the inferior plate, smoothstep between.  Fade into the arch:
    ``d_arch / (d_arch + d_plate)`` through a smoothstep, ``d_plate`` the distance to the nearest plate vertex,
    ``d_arch`` to the nearest vertex of the posterior elements (every region but ``DEFORMABLE``); so both
    plates move exactly rigidly and every vertex of the facets, laminae and processes stays in place."""
    from spinecohort.anatomy.labels import region_id

    lm, v = ref.landmarks, ref.vertices
    idx, w_sup, w_inf, axes, lats = [], [], [], [], []
    for i, lv in enumerate(LEVELS):
        ii = ref.vertebra(i)
        m = fr.normal[(lv, "sup")] + fr.normal[(lv, "inf")]
        m /= np.linalg.norm(m)
        lat = np.array([1.0, 0.0, 0.0]) - m[0] * m
        lat /= np.linalg.norm(lat)
        sup = np.union1d(lm.endplate_sup[lv], lm.endplate_full_sup.get(lv, []))
        inf = np.union1d(lm.endplate_inf[lv], lm.endplate_full_inf.get(lv, []))
        z = v[ii] @ m
        z_hi, z_lo = (v[sup] @ m).min(), (v[inf] @ m).max()
        if z_hi <= z_lo:
            raise ValueError(f"reference {lv}: superior plate reaches below the inferior one along the body axis")
        axial = _smoothstep((z - z_lo) / (z_hi - z_lo))
        arch = ii[~np.isin(ref.region[ii], [region_id(r) for r in DEFORMABLE])]
        d_plate = cKDTree(v[np.concatenate([sup, inf])]).query(v[ii])[0]
        d_arch = cKDTree(v[arch]).query(v[ii])[0]
        fade = _smoothstep(d_arch / np.maximum(d_arch + d_plate, 1e-9))
        idx.append(ii)
        w_sup.append(fade * axial)
        w_inf.append(fade * (1.0 - axial))
        axes.append(m)
        lats.append(lat)
    return BodyMap(tuple(idx), tuple(w_sup), tuple(w_inf), np.array(axes), np.array(lats))


def plate_motion(fr, bm: BodyMap, shape: Shape, i: int, key: str) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of one endplate of vertebra i (``key`` "sup"/"inf"), x -> R x + t in reference mm: the inferior
    plate turned by the wedge change about the medio-lateral axis through its centre (the superior plate keeps
    its tilt, see :func:`spread_disc_change`), then the lift."""
    angle = -np.radians(shape.wedge_deg[i]) if key == "inf" else 0.0
    rot = Rotation.from_rotvec(angle * bm.lateral[i]).as_matrix()
    lift = shape.lift_sup[i] if key == "sup" else shape.lift_inf[i]
    c = fr.centre[(LEVELS[i], key)]
    return rot, c - rot @ c + lift * bm.axis[i]


def shaped_vertices(vertices: np.ndarray, fr, bm: BodyMap, shape: Shape) -> np.ndarray:
    """(N, 3) reference vertices with every body deformed by the patient's plate motions (arch unchanged)."""
    out = vertices.copy()
    for i, ii in enumerate(bm.idx):
        x = vertices[ii]
        move = np.zeros_like(x)
        for key, w in (("sup", bm.w_sup[i]), ("inf", bm.w_inf[i])):
            rot, t = plate_motion(fr, bm, shape, i, key)
            move += w[:, None] * (x @ rot.T + t - x)
        out[ii] = x + move
    return out


def shaped_frames(fr, bm: BodyMap, shape: Shape):
    """The reference frames with every vertebral endplate plane carried by its plate motion (the S1 plate, the
    pelvis and the femoral heads unchanged): the true planes of the shaped vertebrae."""
    centre, normal = dict(fr.centre), dict(fr.normal)
    for i, lv in enumerate(LEVELS):
        for key in ("sup", "inf"):
            rot, t = plate_motion(fr, bm, shape, i, key)
            centre[(lv, key)] = rot @ fr.centre[(lv, key)] + t
            normal[(lv, key)] = rot @ fr.normal[(lv, key)]
    return replace(fr, centre=centre, normal=normal)


def draw_shape(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One patient's disc heights (17,) mm T1-T2 ... L5-S1 and body wedge changes (17,) deg T1 ... L5."""
    disc = DISC_HEIGHT_MEAN_MM + DISC_HEIGHT_SD_MM * np.clip(rng.standard_normal(len(LEVELS)), -CLIP_SD, CLIP_SD)
    wedge = WEDGE_SD_DEG * np.clip(rng.standard_normal(len(LEVELS)), -CLIP_SD, CLIP_SD)
    return disc, wedge


def spread_disc_change(shape: Shape, change_mm: np.ndarray) -> Shape:
    """The plate lifts (reference mm) that change every disc T1-T2 ... L5-S1 by ``change_mm`` (17,): all by the
    upper vertebra's inferior plate, within ``LIFT_MIN_MM`` ... ``LIFT_MAX_MM``.  The superior plates stay: in the thoracic reference the posterior edge
    of a superior plate lies 0.4-2.5 mm from the inferior articular process resting on it, while an inferior
    plate is 13-23 mm from the arch below (5-11 mm in the lumbar levels), so only the inferior one can move
    without driving a body into a facet."""
    lift = np.clip(shape.lift_inf + change_mm, LIFT_MIN_MM, LIFT_MAX_MM)
    return Shape(shape.lift_sup.copy(), lift, shape.wedge_deg)
