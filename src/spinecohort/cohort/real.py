"""The default cohort generator on real bone surfaces: the labeled reference spine posed and varied per patient.

Each patient is the reference (:mod:`spinecohort.anatomy.reference`; Visible Human Male lumbar spine,
sacrum and hip bones, thoracic levels fitted to level-specific shapes) with

* pelvic morphology: the pelvic incidence drawn as in an adult-spinal-deformity cohort
  (:func:`alignment.draw_patient`, clipped to ``PI_RANGE_DEG``) is made by the shape of the pelvis: the
  sacrum and the auricular part of each ilium turn together about the medio-lateral axis through the
  sacro-iliac joints, fading out towards the acetabula (:func:`pelvis_turn_weights`), so the joints stay
  congruent and the acetabula and femoral heads keep their spheres;
* the alignment of :mod:`spinecohort.cohort.alignment`: every vertebra's posterior arch is a rigid body
  (times the patient's overall scale) turned so that the vertebra's mid-axis (the mean of its two endplate
  normals) takes the orientation of the patient's chain, and hinged on the level below at the joint pivot
  (the mid-point of its inferior articular surfaces), so the facet joints stay congruent while the disc in
  front opens or closes;
* body and disc shape (:mod:`spinecohort.cohort.shape`): disc heights drawn per level around published means,
  reached by moving each body's inferior endplate along the body axis (the body takes the difference, the
  arch stays), and a drawn change of every body's wedge (:func:`reach_discs`);
* open joints: from L5-S1 upwards a joint whose two bones cross or whose bodies come closer than
  ``MIN_BODY_GAP_MM`` is opened along its disc axis in ``OPEN_STEP_MM`` steps (:func:`separate`).

Ground truth: the reference endplate planes (rim-band centre and least-squares normal) and head spheres
carried by the imposed rigid plate motions and similarities, and the pelvic incidence of the turned reference pelvis
(:func:`pose_truth`, then :func:`alignment.true_parameters`; no fit of the patient mesh).  Correspondence:
every patient has the reference's vertices and faces.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spinecohort.anatomy.labels import REGIONS
from spinecohort.anatomy.reference import Reference, load_reference
from spinecohort.cohort.alignment import (
    CRITERIA,
    N_POS,
    Chain,
    PatientParameters,
    build_chain,
    draw_patient,
    endplate_frames,
    meets_criteria,
    pos_inf,
    pos_sup,
    rot_x,
    true_parameters,
)
from spinecohort.cohort.landmarks import LEVELS
from spinecohort.cohort.shape import Shape, body_map, draw_shape, shaped_frames, shaped_vertices, spread_disc_change

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReferenceFrames:
    """Endplate centres (mm) and cranial unit normals of the reference, the pelvic geometry."""

    centre: dict  # (level, "sup"|"inf") -> (3,)
    normal: dict
    body_height: np.ndarray  # (17,) centre-to-centre along the mean normal, T1..L5
    disc_height: np.ndarray  # (17,) T1-T2 .. L5-S1
    head_centre: dict  # "L"/"R" -> (3,)
    head_radius: dict
    si_centre: np.ndarray  # (3,) a point on the sacral turn axis
    pi_by_turn: np.ndarray | None = None  # PI (deg) at every TURN_GRID_DEG turn, tabulated by reference_frames


def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(0)
    n = np.linalg.svd(points - c)[2][-1]
    return c, n * np.sign(n[2])


def reference_frames(ref: Reference) -> ReferenceFrames:
    """The reference's frames, with the PI of every tabulated sacral turn (:func:`turn_for_pi`)."""
    fr = _reference_frames(ref)
    return replace(fr, pi_by_turn=np.array([_pelvic_frame(fr, t)[-1] for t in TURN_GRID_DEG]))


def _reference_frames(ref: Reference) -> ReferenceFrames:
    lm, v = ref.landmarks, ref.vertices
    centre, normal = {}, {}
    for key, sets in (("sup", lm.endplate_sup), ("inf", lm.endplate_inf)):
        for lv, idx in sets.items():
            centre[(lv, key)], normal[(lv, key)] = _plane(v[idx])

    def along(upper, lower):
        m = normal[upper] + normal[lower]
        return float((centre[upper] - centre[lower]) @ (m / np.linalg.norm(m)))

    body = np.array([along((lv, "sup"), (lv, "inf")) for lv in LEVELS])
    below = list(LEVELS[1:]) + ["S1"]
    disc = np.array([along((lv, "inf"), (lo, "sup")) for lv, lo in zip(LEVELS, below)])
    heads = {}
    for s in ("L", "R"):
        p = v[lm.femoral_head[s]]
        a = np.c_[2.0 * p, np.ones(len(p))]
        sol = np.linalg.lstsq(a, np.sum(p**2, axis=1), rcond=None)[0]
        heads[s] = (sol[:3], float(np.sqrt(sol[3] + sol[:3] @ sol[:3])))
    # the sacro-iliac joints: the hip-bone vertices closest to the sacrum, one cluster per side
    sac = np.isin(ref.region, [11, 12])
    ilium = np.isin(ref.region, [13, 14])
    from scipy.spatial import cKDTree

    d = cKDTree(v[sac]).query(v[ilium])[0]
    si = v[ilium][d < np.quantile(d, 0.01)].mean(0)
    return ReferenceFrames(
        centre,
        normal,
        body,
        disc,
        {k: h[0] for k, h in heads.items()},
        {k: h[1] for k, h in heads.items()},
        si,
    )


def _pelvic_frame(fr: ReferenceFrames, turn_deg: float):
    """S1 centre and normal after the sacral turn, the hip axis (mid-point), lateral axis, PI (deg)."""
    rot = Rotation.from_rotvec(np.radians(turn_deg) * np.array([1.0, 0.0, 0.0])).as_matrix()
    c = fr.si_centre + (fr.centre[("S1", "sup")] - fr.si_centre) @ rot.T
    n = rot @ fr.normal[("S1", "sup")]
    ha = 0.5 * (fr.head_centre["L"] + fr.head_centre["R"])
    lat = fr.head_centre["R"] - fr.head_centre["L"]
    lat /= np.linalg.norm(lat)
    # PI in the sagittal plane normal to the hip axis, as the measurement defines it
    up = np.array([0.0, 0.0, 1.0]) - lat[2] * lat
    up /= np.linalg.norm(up)
    ant = np.cross(up, lat)
    ant *= np.sign(ant[1])

    def sagittal(x):
        return float(np.degrees(np.arctan2(x @ ant, x @ up)))

    pi = sagittal(n) - sagittal(c - ha)
    return rot, c, n, ha, lat, up, ant, pi


def pelvis_similarity(fr: ReferenceFrames, turn_deg: float, pt_deg: float, scale: float):
    """(R, s, t) placing the turned reference pelvis with the hip axis at the origin, the hip axis along x and
    the S1 centre at pelvic tilt ``pt_deg``; also the patient's PI, pelvic radius and sacral turn rotation."""
    rot_sac, c, n, ha, lat, up, ant, pi = _pelvic_frame(fr, turn_deg)
    d = c - ha
    d_sag = d - (d @ lat) * lat
    radius = float(np.linalg.norm(d_sag))
    # reference basis (lat, d_sag direction, its perpendicular) -> patient (x, rot_x(PT) z, rot_x(PT) y)
    e2 = d_sag / radius
    src = np.stack([lat, np.cross(e2, lat), e2], axis=1)
    dst = np.stack([[1.0, 0.0, 0.0], rot_x(pt_deg) @ [0.0, 1.0, 0.0], rot_x(pt_deg) @ [0.0, 0.0, 1.0]], axis=1)
    r = dst @ src.T
    t = -scale * r @ ha
    return r, scale, t, rot_sac, pi, radius * scale


#: pelvic incidence (deg) the pelvic morphology is drawn in: ``draw_patient``'s PI (mean 58, SD 9 deg, adult
#: spinal deformity cohorts) clipped to the range the sacral turn reaches without folding the ilium
PI_RANGE_DEG = (38.0, 72.0)
#: sacral turns (deg) tabulated to invert PI(turn)
TURN_GRID_DEG = np.linspace(-50.0, 25.0, 151)


def turn_for_pi(fr: ReferenceFrames, pi_deg: np.ndarray) -> np.ndarray:
    """The sacral turn (deg) that gives the pelvic incidence ``pi_deg`` (PI falls monotonically with the turn)."""
    pis = fr.pi_by_turn if fr.pi_by_turn is not None else [_pelvic_frame(fr, t)[-1] for t in TURN_GRID_DEG]
    pis = np.asarray(pis)
    return np.interp(pi_deg, pis[::-1], TURN_GRID_DEG[::-1])


def draw_real_patient(rng: np.random.Generator, pid: str, fr: ReferenceFrames) -> tuple[PatientParameters, float]:
    """A patient of the generic draw whose pelvic morphology gives the drawn PI: the sacral turn that makes the
    reference pelvis's PI the drawn one (within ``PI_RANGE_DEG``); the drawn PI - LL mismatch and PT are kept
    (PT within [12, PI - 12] deg).  Returns the patient (with the exact PI of its pelvis) and the turn."""
    p = draw_patient(rng, pid)
    turn = float(turn_for_pi(fr, np.clip(p.PI, *PI_RANGE_DEG)))
    pi = _pelvic_frame(fr, turn)[-1]
    mismatch = p.PI - p.LL
    pt = float(np.clip(p.PT, min(12.0, pi - 12.0), pi - 12.0))
    ll = float(np.clip(pi - mismatch, 4.0, 75.0))
    return replace(p, PI=pi, PT=pt, LL=ll), turn


#: hip-bone vertices within this distance (mm) of a femoral-head surface keep the acetabulum's pose; those
#: within SI_CONTACT_MM of the sacrum turn with it
ACETABULUM_MARGIN_MM, SI_CONTACT_MM = 12.0, 3.0


def pelvis_turn_weights(ref: Reference, fr: ReferenceFrames) -> np.ndarray:
    """(N,) fraction of the sacral turn every pelvis vertex takes: 1 on the sacrum, 0 on the femurs and within
    ``ACETABULUM_MARGIN_MM`` of a femoral head, and on the hip bones a smoothstep of the ratio of the distances
    to the acetabulum and to the sacrum (1 at the sacro-iliac joint): the sacrum and the auricular part of the
    ilium turn together (the joint stays congruent) while the acetabula and heads keep their spheres, so PI
    changes by the shape of the pelvis."""
    v = ref.vertices
    sac = np.isin(ref.region, [11, 12])
    hip = np.isin(ref.region, [13, 14])
    w = np.zeros(len(v))
    w[sac] = 1.0
    d_si = np.clip(cKDTree(v[sac]).query(v[hip])[0] - SI_CONTACT_MM, 0.0, None)
    d_ac = np.min([np.linalg.norm(v[hip] - fr.head_centre[k], axis=1) - fr.head_radius[k] for k in ("L", "R")], axis=0)
    d_ac = np.clip(d_ac - ACETABULUM_MARGIN_MM, 0.0, None)
    t = d_ac / np.maximum(d_ac + d_si, 1e-9)
    w[hip] = t * t * (3.0 - 2.0 * t)
    return w


def turn_pelvis(x: np.ndarray, w: np.ndarray, fr: ReferenceFrames, turn_deg: float) -> np.ndarray:
    """Reference pelvis vertices (N, 3) mm turned by ``w * turn_deg`` about the medio-lateral axis through the
    sacro-iliac joints (the sacral turn at w = 1)."""
    a = np.radians(turn_deg) * w
    c, s = np.cos(a), np.sin(a)
    d = x - fr.si_centre
    out = d.copy()
    out[:, 1] = c * d[:, 1] - s * d[:, 2]
    out[:, 2] = s * d[:, 1] + c * d[:, 2]
    return out + fr.si_centre


def joint_pivots(ref: Reference) -> np.ndarray:
    """(17, 3) reference pivot (mm) of the joint below every level T1..L5: the mid-point of the centroids of
    the left and right inferior articular surfaces.  A rotation about it keeps both facet joints nearly in
    place (they lie on its medio-lateral line) and opens or closes the disc in front."""
    return np.array(
        [
            0.5
            * sum(ref.vertices[ref.sets[f"facet_surface_inf_{s}"][lv].astype(int)].mean(0) for s in ("left", "right"))
            for lv in LEVELS
        ]
    )


def _mid_frames(n_sup: np.ndarray, n_inf: np.ndarray) -> np.ndarray:
    """(K, 3, 3) frames of the mid-axes (mean of the two endplate normals) of K vertebrae."""
    m = n_sup + n_inf
    return endplate_frames(m / np.linalg.norm(m, axis=1, keepdims=True))


@dataclass
class Pose:
    """Similarities of one patient in the construction frame: ``x -> s R x + t`` per vertebra (T1..L5), the
    pelvis's similarity after its sacral turn, and the turn."""

    scale: float
    rot: np.ndarray  # (17, 3, 3)
    trans: np.ndarray  # (17, 3) mm
    pelvis: tuple  # (r (3, 3), t (3,)) applied after turn_pelvis
    turn_deg: float

    def sacrum(self, fr: ReferenceFrames, x: np.ndarray) -> np.ndarray:
        return self.scale * turn_pelvis(x, np.ones(len(x)), fr, self.turn_deg) @ self.pelvis[0].T + self.pelvis[1]

    def vertebra(self, i: int, x: np.ndarray) -> np.ndarray:
        return self.scale * x @ self.rot[i].T + self.trans[i]


def pose_column(p: PatientParameters, turn_deg: float, fr: ReferenceFrames, pivots: np.ndarray, open_mm: np.ndarray):
    """Every vertebra a rigid body (times the patient's scale), turned to the orientation the patient's chain
    (:func:`alignment.build_chain`) gives its mid-axis, and hinged on the level below at the joint pivot:
    the pivot point of both levels coincides, then the upper one is lifted by ``open_mm`` (17,) along the disc's
    mean endplate normal.  Returns the Pose (with the patient's PI, pelvic radius and hip width set in p)."""
    r, s, t, rot_sac, pi, radius = pelvis_similarity(fr, turn_deg, p.PT, p.scale)
    heads = {k: s * r @ c + t for k, c in fr.head_centre.items()}
    p = replace(p, PI=pi, pelvic_radius=radius, fh_radius=fr.head_radius["L"] * s)
    p = replace(p, hip_width=float(np.linalg.norm(heads["R"] - heads["L"])))
    target = build_chain(p, fr.body_height, fr.disc_height)
    pose = Pose(s, np.empty((17, 3, 3)), np.empty((17, 3)), (r, t), turn_deg)
    lower_n = r @ rot_sac @ fr.normal[("S1", "sup")]
    n_ref = {key: np.array([fr.normal[(lv, key)] for lv in LEVELS]) for key in ("sup", "inf")}
    m_ref = _mid_frames(n_ref["sup"], n_ref["inf"])
    idx = np.arange(len(LEVELS))
    m_tgt = _mid_frames(target.normals[pos_sup(idx)], target.normals[pos_inf(idx)])
    rots = m_tgt @ np.transpose(m_ref, (0, 2, 1))
    for i in range(len(LEVELS) - 1, -1, -1):
        lv = LEVELS[i]
        rot = rots[i]
        below = pose.sacrum(fr, pivots[i][None])[0] if i == len(LEVELS) - 1 else pose.vertebra(i + 1, pivots[i])
        axis = rot @ fr.normal[(lv, "inf")] + lower_n
        pose.rot[i] = rot
        pose.trans[i] = below - s * rot @ pivots[i] + open_mm[i] * axis / np.linalg.norm(axis)
        lower_n = rot @ fr.normal[(lv, "sup")]
    return pose, p


def posed_chain(pose: Pose, fr: ReferenceFrames) -> Chain:
    """The chain of the reference endplate planes (centre, normal; ``fr`` of the shaped vertebrae) carried by
    the imposed similarities: the true endplates of a posed patient, no fit of its mesh."""
    centres, normals = np.empty((N_POS, 3)), np.empty((N_POS, 3))
    centres[0] = pose.sacrum(fr, fr.centre[("S1", "sup")][None])[0]
    normals[0] = pose.pelvis[0] @ _pelvic_frame(fr, pose.turn_deg)[0] @ fr.normal[("S1", "sup")]
    for i, lv in enumerate(LEVELS):
        for pos, key in ((pos_sup(i), "sup"), (pos_inf(i), "inf")):
            centres[pos] = pose.vertebra(i, fr.centre[(lv, key)])
            normals[pos] = pose.rot[i] @ fr.normal[(lv, key)]
    sag = np.degrees(np.arctan2(normals[:, 1], normals[:, 2]))
    cor = np.degrees(np.arctan2(normals[:, 0], normals[:, 2]))
    m = normals[1:] + normals[:-1]
    lengths = np.einsum("ij,ij->i", centres[1:] - centres[:-1], m / np.linalg.norm(m, axis=1, keepdims=True))
    frames = endplate_frames(normals)
    return Chain(sag, cor, normals, centres, frames, lengths)


def pose_truth(p: PatientParameters, pose: Pose, fr: ReferenceFrames, s1_rim: np.ndarray) -> dict:
    """The true parameters of a posed patient: :func:`posed_chain`, then :func:`alignment.true_parameters`."""
    truth = true_parameters(p, posed_chain(pose, fr), s1_rim)
    truth.update(
        {
            "FH_radius_L": fr.head_radius["L"] * pose.scale,
            "FH_radius_R": fr.head_radius["R"] * pose.scale,
            "HA_width": p.hip_width,
            "sacral_turn_deg": pose.turn_deg,
        }
    )
    return truth


def aim(p: PatientParameters, turn_deg: float, fr: ReferenceFrames, pivots: np.ndarray, s1_rim: np.ndarray):
    """The patient with its chain targets corrected so that the rigid column has the drawn LL, T4-T12 and
    T1-T4 kyphosis: the reference's own body wedges (kept by the rigid vertebrae) shift the endplates at the
    ends of each span from the chain's; two fixed-point steps leave under 0.1 deg."""
    goal = {"LL": p.LL, "TK_T4T12": p.TK_T4T12, "TK_T1T4": p.TK_T1T4}
    q = p
    for _ in range(3):
        pose, posed = pose_column(q, turn_deg, fr, pivots, np.zeros(len(LEVELS)))
        t = pose_truth(posed, pose, fr, pose.sacrum(fr, s1_rim))
        got = {"LL": t["LL"], "TK_T4T12": t["TK_T4T12"], "TK_T1T4": t["TK_T1T12"] - t["TK_T4T12"]}
        q = replace(q, **{k: getattr(q, k) + goal[k] - got[k] for k in goal})
    return q


def reach_discs(p, turn_deg, fr, bm, shape, disc_mm, pivots, n_iter: int = 3):
    """The patient's plate lifts that give its posed column the disc heights ``disc_mm`` (17,) T1-T2 ... L5-S1
    (:func:`shape.spread_disc_change`; a lift moves no joint pivot, so the pose stays and three fixed-point
    steps leave under 0.01 mm where the lift stays inside its range).  Returns the Shape."""
    for _ in range(n_iter):
        frs = shaped_frames(fr, bm, shape)
        pose, _ = pose_column(p, turn_deg, frs, pivots, np.zeros(len(LEVELS)))
        now = posed_chain(pose, frs).lengths[0::2][::-1]  # the chain lists the discs from L5-S1 upwards
        shape = spread_disc_change(shape, (disc_mm - now) / pose.scale)
    return shape


def pose_vertices(
    pose: Pose, ref: Reference, fr: ReferenceFrames, pelvis_w: np.ndarray, vertices: np.ndarray | None = None
) -> np.ndarray:
    """(N, 3) mm: every vertebra by its similarity, the pelvis turned by its weights then placed; ``vertices``:
    the patient's shaped reference (:func:`shape.shaped_vertices`), the reference's own by default."""
    v = ref.vertices if vertices is None else vertices
    out = np.empty_like(v)
    pel = ref.level < 0
    out[pel] = pose.scale * turn_pelvis(v[pel], pelvis_w[pel], fr, pose.turn_deg) @ pose.pelvis[0].T + pose.pelvis[1]
    for i in range(len(LEVELS)):
        idx = ref.vertebra(i)
        out[idx] = pose.vertebra(i, v[idx])
    return out


#: closest body-to-body distance (mm) every disc keeps; a joint whose bones cross or whose bodies come closer
#: is opened along its disc axis (the imposed disc height grows, so the truth follows)
MIN_BODY_GAP_MM = 1.0
OPEN_STEP_MM = 0.5
#: the most a joint is opened (mm); a patient whose joint needs more is not drawn (at L5-S1 a large coronal
#: tilt of the disc, the lower end of a long curve, presses the L5 inferior facet into the sacrum)
MAX_OPEN_MM = 5.0


def separate(p, turn, ref, fr, pivots, pelvis_w, pairs, bodies, max_open_mm: float = MAX_OPEN_MM, vertices=None):
    """Pose a patient with every joint from L5-S1 upwards opened in ``OPEN_STEP_MM`` steps until its two bones
    do not cross and their bodies keep ``MIN_BODY_GAP_MM``; returns vertices, pose, patient, openings (mm), or
    None when a joint needs more than ``max_open_mm``.  ``fr`` and ``vertices``: the patient's shaped frames
    and reference vertices (the reference's by default)."""
    from spinecohort.anatomy.contacts import pair_contact

    shaped = ref.vertices if vertices is None else vertices
    opening = np.zeros(len(LEVELS))
    pose, q = pose_column(p, turn, fr, pivots, opening)
    v = pose_vertices(pose, ref, fr, pelvis_w, shaped)
    # the bones below joint i are settled when it is opened, and opening it moves only the bones above
    for i in range(len(LEVELS) - 1, -1, -1):
        idx = ref.vertebra(i)
        lower = cKDTree(v[bodies[i + 1]])
        while True:
            pose, q = pose_column(p, turn, fr, pivots, opening)
            v[idx] = pose.vertebra(i, shaped[idx])
            short = MIN_BODY_GAP_MM - float(lower.query(v[bodies[i]])[0].min())
            # the (costly) crossing test only once the bodies keep their gap; a gap short by d needs at least d
            if short <= 0 and pair_contact(v, pairs[i])[0] == 0:
                break
            if opening[i] >= max_open_mm:
                return None  # a joint this far apart is no longer a disc: the caller draws another patient
            opening[i] = min(opening[i] + OPEN_STEP_MM * max(1.0, np.ceil(short / OPEN_STEP_MM)), max_open_mm)
    return v, pose, q, opening


def morton_codes(points_mm: np.ndarray, bits: int = 10) -> np.ndarray:
    """(n,) Z-order (Morton) codes of points on a 2^bits grid over their bounding box: nearby points get
    nearby codes."""
    p = points_mm - points_mm.min(0)
    cell = (p / max(float(np.ptp(points_mm, 0).max()), 1e-12) * (2**bits - 1)).astype(np.uint64)
    code = np.zeros(len(p), dtype=np.uint64)
    for b in range(bits):
        for axis in range(3):
            code |= ((cell[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + axis)
    return code


def reference_sites(ref: Reference) -> dict[str, np.ndarray]:
    """The reference's facet articular surfaces, ligament insertion sites and labeled pedicles
    (``pedicle_<side>/<level>``, the hex pedicles' geometry, `spinecohort.fe.pedicles`) as `Landmarks.sites`
    (``"<set>/<level>"`` -> vertex indices): every model of the real cohort has the reference's vertex numbering,
    so these sets name the same anatomy on each of them."""
    out = {
        f"{name}/{lv}": np.asarray(v, dtype=np.int64)
        for name, per in ref.sets.items()
        if name.startswith(("facet_surface_", "site_", "anchor_"))
        for lv, v in per.items()
        if len(v)
    }
    for side in ("left", "right"):
        label = REGIONS.index(f"pedicle_{side}")
        for i, lv in enumerate(LEVELS):
            v = np.flatnonzero((ref.level == i) & (ref.region == label))
            if len(v):
                out[f"pedicle_{side}/{lv}"] = v.astype(np.int64)
    return out


def first_use_reference(ref: Reference) -> Reference:
    """The reference with its faces sorted along a Z-order curve and its vertices numbered in order of first use
    by those faces, every index set remapped.  First use: an STL written and read back (vertices merged in
    first-occurrence order) keeps the order.  Z-order: neighbouring vertices in the stored arrays are neighbours
    in space, which the store's bitshuffle-zstd compresses 13 % better than the remeshed order."""
    from spinecohort.cohort.synthetic import first_use_order

    faces = ref.faces[np.argsort(morton_codes(ref.vertices)[ref.faces].min(1), kind="stable")]
    order = first_use_order(faces, len(ref.vertices))
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    lm = ref.landmarks

    def remap(sets):
        return {k: np.sort(inv[v]) for k, v in sets.items()}

    # the facet surfaces and ligament sites ride with the landmarks, so the hex template gets them (`reference_sites`)
    lm = replace(lm, sites={**lm.sites, **reference_sites(ref)})
    new_lm = replace(lm.renumbered(order), meta={**lm.meta, "generator": "spinecohort.cohort.real"})
    return Reference(
        ref.vertices[order],
        inv[faces],
        ref.region[order],
        ref.level[order],
        ref.side[order],
        new_lm,
        {name: remap(per) for name, per in ref.sets.items()},
        ref.build,
    )


def generate_real_cohort(
    n_patients: int = 42,
    seed: int = 20240549,
    criteria: dict = CRITERIA,
    max_candidates: int = 100000,
    reference: str | None = None,
    progress=None,
):
    """Draw patients on the reference until ``n_patients`` meet the inclusion criteria."""
    from spinecohort.anatomy.contacts import bone_pairs
    from spinecohort.cohort.synthetic import SyntheticCohort

    ref = first_use_reference(load_reference(reference))
    fr = reference_frames(ref)
    pivots = joint_pivots(ref)
    pelvis_w = pelvis_turn_weights(ref, fr)
    bm = body_map(ref, fr)
    pairs = bone_pairs(ref.level, ref.region, ref.vertices[:, 0], ref.faces)
    bodies = [np.flatnonzero((ref.level == i) & (ref.region == 0)) for i in range(len(LEVELS))]
    bodies.append(np.flatnonzero(ref.region == 12))  # the S1 plate region
    s1_rim_ref = ref.vertices[ref.landmarks.rim_sup["S1"]]
    rng = np.random.default_rng(seed)
    verts, rows, n_cand, n_apart, n_late, openings = [], [], 0, 0, 0, []
    while len(verts) < n_patients:
        if n_cand >= max_candidates:
            raise RuntimeError(f"only {len(verts)} of {max_candidates} candidates met the criteria {criteria}")
        n_cand += 1
        p, turn = draw_real_patient(rng, f"P{len(verts) + 1:02d}", fr)
        disc_mm, wedge_deg = draw_shape(rng)
        shape = Shape(np.zeros(len(LEVELS)), np.zeros(len(LEVELS)), wedge_deg)
        p = aim(p, turn, shaped_frames(fr, bm, shape), pivots, s1_rim_ref)
        shape = reach_discs(p, turn, fr, bm, shape, disc_mm, pivots)
        frs = shaped_frames(fr, bm, shape)
        pose, q = pose_column(p, turn, frs, pivots, np.zeros(len(LEVELS)))
        if not meets_criteria(pose_truth(q, pose, frs, pose.sacrum(fr, s1_rim_ref)), criteria):
            continue  # cheap screen on the closed column; the opened one is checked again below
        shaped = shaped_vertices(ref.vertices, fr, bm, shape)
        posed = separate(p, turn, ref, frs, pivots, pelvis_w, pairs, bodies, vertices=shaped)
        if posed is None:
            n_apart += 1
            continue
        v, pose, q, opening = posed
        openings.append(opening)
        truth = pose_truth(q, pose, frs, pose.sacrum(fr, s1_rim_ref))
        if not meets_criteria(truth, criteria):
            n_late += 1
            continue
        placement = Rotation.from_euler("z", q.axial_rotation_deg, degrees=True).as_matrix()
        verts.append(v @ placement.T + q.translation)
        rows.append({"ID": q.ID, "age": round(q.age, 1), "sex": q.sex, **truth})
        if progress is not None:
            progress(len(verts), n_patients)
    log.info(
        "accepted %d of %d candidates (%.0f %%); %d met the criteria on the closed column but not once opened",
        n_patients,
        n_cand,
        100 * n_patients / n_cand,
        n_late,
    )
    opened = np.array(openings)
    log.info(
        "%d candidates needed a joint opened over %.1f mm; joints opened by %.2f mm on average, at most %.1f mm",
        n_apart,
        MAX_OPEN_MM,
        opened.mean(),
        opened.max(),
    )
    log.info(
        "joints opened per disc T1-T2 ... L5-S1 (share of accepted and candidate patients, mean mm): %s",
        ", ".join(f"{lv} {np.mean(o > 0):.0%} {o.mean():.2f}" for lv, o in zip(LEVELS, opened.T)),
    )
    ids = [r["ID"] for r in rows]
    return SyntheticCohort(ids, np.stack(verts), ref.faces, ref.landmarks, pd.DataFrame(rows), n_cand)
