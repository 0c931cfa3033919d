"""The default cohort generator on real bone surfaces: the labeled reference spine posed and varied per patient.

Each patient is the reference (:mod:`spinecohort.anatomy.reference`; Visible Human Male lumbar spine,
sacrum and hip bones, thoracic levels fitted to level-specific shapes) with

* the alignment of :mod:`spinecohort.cohort.alignment`: every endplate of the reference is moved onto the
  patient's endplate chain (centre and frame), so the sagittal and coronal tilts, the lordosis and kyphosis
  and the wedging of every disc and body are the imposed ones;
* shape variation: overall size (the patient's scale), central body and disc heights (the reference's, times
  the patient's disc factor and a body-height factor), and the pelvis: the sacrum is turned about the
  medio-lateral axis through the sacro-iliac joints by an angle drawn per patient, which changes the
  pelvic incidence (PI varies because the pelvis differs, not by posture alone).

How a vertebra follows its two endplates: each endplate ``e`` gets the similarity
``T_e(x) = C_e + s R_e (x - c_e)`` taking the reference endplate (centre ``c_e``, frame of its rim-band plane)
to the patient's (``C_e``, frame of the chain); a vertex at relative height ``w`` between the reference
inferior (0) and superior (1) endplate centres, clipped to [0, 1], moves to ``(1 - w) T_inf(x) + w T_sup(x)``.
The endplate patches and rim bands have ``w`` exactly 0 or 1, so they move rigidly and the plane and centre
the measurement fits are exactly the imposed ones.  The posterior arch near a facet joint (within
``JOINT_RADIUS_MM`` of an articular surface) or hanging below the inferior endplate (fully at ``HANG_MM``)
blends towards the map shared by both sides of the joint, and a disc that would bring two bodies closer than
``MIN_BODY_GAP_MM`` is made higher (its imposed height, hence the truth, follows).  The pelvis, sacrum and femoral heads move as one
similarity (after the sacral turn), so the head spheres stay spheres.

Ground truth: the chain's imposed angles and positions (:func:`alignment.true_parameters`) with the pelvic
incidence, pelvic radius, head radii and hip width taken from the transformed reference planes and spheres
(no fit of the patient mesh).  Correspondence: every patient has the reference's vertices and faces.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from spinecohort.anatomy.reference import Reference, load_reference
from spinecohort.cohort.alignment import (
    CRITERIA,
    PatientParameters,
    build_chain,
    draw_patient,
    endplate_frame,
    meets_criteria,
    pos_inf,
    pos_sup,
    rot_x,
    true_parameters,
)
from spinecohort.cohort.landmarks import LEVELS

log = logging.getLogger(__name__)

#: SD (deg) and clip (deg) of the sacral turn that varies PI about the reference's
SACRAL_TURN_SD_DEG, SACRAL_TURN_MAX_DEG = 6.0, 12.0
#: SD of the per-level body-height factor
BODY_HEIGHT_SD = 0.04


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


def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(0)
    n = np.linalg.svd(points - c)[2][-1]
    return c, n * np.sign(n[2])


def reference_frames(ref: Reference) -> ReferenceFrames:
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


def _sag(v: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(v[1], v[2])))


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


def draw_real_patient(rng: np.random.Generator, pid: str, fr: ReferenceFrames) -> tuple[PatientParameters, float]:
    """A patient of the generic draw with the pelvic incidence of the turned reference pelvis: the drawn
    PI - LL mismatch and PT are kept (PT within [12, PI - 12] deg); returns the sacral turn too."""
    p = draw_patient(rng, pid)
    turn = float(np.clip(rng.normal(0.0, SACRAL_TURN_SD_DEG), -SACRAL_TURN_MAX_DEG, SACRAL_TURN_MAX_DEG))
    pi = _pelvic_frame(fr, turn)[-1]
    mismatch = p.PI - p.LL
    pt = float(np.clip(p.PT, min(12.0, pi - 12.0), pi - 12.0))
    ll = float(np.clip(pi - mismatch, 4.0, 75.0))
    return replace(p, PI=pi, PT=pt, LL=ll), turn


def _vertebra_weights(ref: Reference, fr: ReferenceFrames) -> np.ndarray:
    """(N,) relative height of every vertebra vertex between its inferior (0) and superior (1) endplate."""
    w = np.zeros(len(ref.vertices))
    for i, lv in enumerate(LEVELS):
        idx = ref.vertebra(i)
        c0, c1 = fr.centre[(lv, "inf")], fr.centre[(lv, "sup")]
        axis = c1 - c0
        w[idx] = np.clip((ref.vertices[idx] - c0) @ axis / (axis @ axis), 0.0, 1.0)
        for key, val in (("sup", 1.0), ("inf", 0.0)):
            w[ref.sets[f"endplate_full_{key}"][lv]] = val
            w[getattr(ref.landmarks, f"endplate_{key}")[lv]] = val
    return w


def rot_sac_point(fr: ReferenceFrames, rot_sac: np.ndarray) -> np.ndarray:
    """The reference S1 centre after the sacral turn."""
    return fr.si_centre + rot_sac @ (fr.centre[("S1", "sup")] - fr.si_centre)


#: support radius (mm) of the facet-joint weight: posterior-element vertices within it of an articular
#: surface follow the joint's shared transform
JOINT_RADIUS_MM = 12.0
HANG_MM = 8.0


def _joint_weights(ref: Reference) -> tuple[np.ndarray, np.ndarray]:
    """(N,) weights of every vertebra vertex towards its inferior and superior facet joints: 1 on the
    articular surface, falling as (1 - d / R)^2 to 0 at ``JOINT_RADIUS_MM``, 0 on the vertebral body."""
    from scipy.spatial import cKDTree

    v = ref.vertices
    out = {"inf": np.zeros(len(v)), "sup": np.zeros(len(v))}
    fr = reference_frames(ref)
    for i, lv in enumerate(LEVELS):
        idx = ref.vertebra(i)
        post = idx[ref.region[idx] != 0]
        # the arch below the inferior endplate (the caudally hanging processes, behind the next level) moves
        # with the disc's lower side as it gets deeper: fully at HANG_MM below
        c0, c1 = fr.centre[(lv, "inf")], fr.centre[(lv, "sup")]
        axis = (c1 - c0) / np.linalg.norm(c1 - c0)
        out["inf"][post] = np.clip(-(v[post] - c0) @ axis / HANG_MM, 0.0, 1.0)
        for key in ("inf", "sup"):
            if key == "sup" and i == 0:
                continue  # T1's superior facets have no partner in the model
            surf = np.concatenate([ref.sets[f"facet_surface_{key}_{s}"].get(lv, []) for s in ("left", "right")])
            if len(surf) == 0:
                continue
            d = cKDTree(v[surf.astype(int)]).query(v[post])[0]
            out[key][post] = np.maximum(out[key][post], np.clip(1.0 - d / JOINT_RADIUS_MM, 0.0, 1.0) ** 2)
    return out["inf"], out["sup"]


def build_real_patient(
    p, turn_deg, ref, fr, weights, body_factor, joints=None, disc_mm=None
) -> tuple[np.ndarray, dict]:
    """Vertices (N, 3) mm of one patient in its placed frame, and its true parameters."""
    r, s, t, rot_sac, pi, radius = pelvis_similarity(fr, turn_deg, p.PT, p.scale)
    heads = {k: s * r @ c + t for k, c in fr.head_centre.items()}
    p = replace(
        p,
        PI=pi,
        pelvic_radius=radius,
        fh_radius=fr.head_radius["L"] * s,
        hip_width=float(np.linalg.norm(heads["R"] - heads["L"])),
    )
    chain = build_chain(p, fr.body_height * body_factor, fr.disc_height if disc_mm is None else disc_mm)
    # the S1 centre's medio-lateral offset from the hip-axis midpoint: the column stands on the real plate
    s1 = s * r @ rot_sac_point(fr, rot_sac) + t
    chain.centres += s1 - chain.centres[0]
    v = ref.vertices
    out = np.empty_like(v)
    pelvis = ref.level < 0
    sac = np.isin(ref.region, [11, 12])
    base = v.copy()
    base[sac] = fr.si_centre + (v[sac] - fr.si_centre) @ rot_sac.T
    out[pelvis] = s * base[pelvis] @ r.T + t

    def endplate_map(i: int, key: str, x: np.ndarray) -> np.ndarray:
        if i == len(LEVELS):  # the S1 plate moves with the pelvis (after the sacral turn)
            return s * (fr.si_centre + (x - fr.si_centre) @ rot_sac.T) @ r.T + t
        lv = LEVELS[i]
        pos = pos_sup(i) if key == "sup" else pos_inf(i)
        rot = chain.frames[pos] @ endplate_frame(fr.normal[(lv, key)]).T
        return chain.centres[pos] + s * (x - fr.centre[(lv, key)]) @ rot.T

    u_inf, u_sup = joints if joints is not None else (np.zeros(len(v)), np.zeros(len(v)))
    for i in range(len(LEVELS)):
        idx = ref.vertebra(i)
        x, w = v[idx], weights[idx, None]
        own = (1.0 - w) * endplate_map(i, "inf", x) + w * endplate_map(i, "sup", x)
        # a facet joint's two sides move with the same map, the mean of the two endplates facing across the
        # disc: the joint keeps the reference's congruence and clearance whatever the disc does
        below = 0.5 * (endplate_map(i, "inf", x) + endplate_map(i + 1, "sup", x))
        a, b = u_inf[idx, None], u_sup[idx, None]
        out[idx] = (1.0 - a - b) * own + a * below
        if i > 0:
            above = 0.5 * (endplate_map(i - 1, "inf", x) + endplate_map(i, "sup", x))
            out[idx] += b * above
    s1_rim = out[ref.landmarks.rim_sup["S1"]]
    truth = true_parameters(p, chain, s1_rim)
    truth.update(
        {
            "FH_radius_L": fr.head_radius["L"] * s,
            "FH_radius_R": fr.head_radius["R"] * s,
            "HA_width": p.hip_width,
            "sacral_turn_deg": turn_deg,
        }
    )
    placement = Rotation.from_euler("z", p.axial_rotation_deg, degrees=True).as_matrix()
    return out @ placement.T + p.translation, truth


#: closest body-to-body distance (mm) every disc of a patient keeps; a narrowed or wedged disc that would come
#: closer is made higher (the disc height is imposed, so the truth follows)
MIN_BODY_GAP_MM = 1.0


def open_discs(p, turn, ref, fr, weights, body_factor, joints, bodies, rounds: int = 4):
    """`build_real_patient` with every disc high enough that the bodies keep ``MIN_BODY_GAP_MM`` apart."""
    from scipy.spatial import cKDTree

    disc = fr.disc_height.copy()
    for _ in range(rounds):
        v, truth = build_real_patient(p, turn, ref, fr, weights, body_factor, joints, disc)
        gaps = np.array([cKDTree(v[bodies[k]]).query(v[bodies[k + 1]])[0].min() for k in range(len(LEVELS))])
        short = gaps < MIN_BODY_GAP_MM
        if not short.any():
            break
        disc[short] += (MIN_BODY_GAP_MM - gaps[short] + 0.5) / (p.disc_factor[short] * p.scale)
    return v, truth


def first_use_reference(ref: Reference) -> Reference:
    """The reference with its vertices numbered in order of first use by the faces, so that an STL written and
    read back (vertices merged in first-occurrence order) keeps the order, and every index set remapped."""
    from spinecohort.cohort.synthetic import first_use_order

    order = first_use_order(ref.faces, len(ref.vertices))
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    lm = ref.landmarks

    def remap(sets):
        return {k: np.sort(inv[v]) for k, v in sets.items()}

    new_lm = replace(
        lm,
        part=lm.part[order],
        endplate_sup=remap(lm.endplate_sup),
        endplate_inf=remap(lm.endplate_inf),
        rim_sup=remap(lm.rim_sup),
        rim_inf=remap(lm.rim_inf),
        femoral_head=remap(lm.femoral_head),
        body=remap(lm.body),
        pubic_symphysis=np.sort(inv[lm.pubic_symphysis]),
        anchors={k: inv[v] for k, v in lm.anchors.items()},
        meta={**lm.meta, "generator": "spinecohort.cohort.real"},
    )
    return Reference(
        ref.vertices[order],
        inv[ref.faces],
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
    from spinecohort.cohort.synthetic import SyntheticCohort

    ref = first_use_reference(load_reference(reference))
    fr = reference_frames(ref)
    weights = _vertebra_weights(ref, fr)
    joints = _joint_weights(ref)
    bodies = [np.flatnonzero((ref.level == i) & (ref.region == 0)) for i in range(len(LEVELS))]
    bodies.append(np.flatnonzero(ref.region == 12))  # the S1 plate region
    rng = np.random.default_rng(seed)
    verts, rows, n_cand = [], [], 0
    while len(verts) < n_patients:
        if n_cand >= max_candidates:
            raise RuntimeError(f"only {len(verts)} of {max_candidates} candidates met the criteria {criteria}")
        n_cand += 1
        p, turn = draw_real_patient(rng, f"P{len(verts) + 1:02d}", fr)
        body_factor = rng.normal(1.0, BODY_HEIGHT_SD, size=len(LEVELS))
        v, truth = open_discs(p, turn, ref, fr, weights, body_factor, joints, bodies)
        if not meets_criteria(truth, criteria):
            continue
        verts.append(v)
        rows.append({"ID": p.ID, "age": round(p.age, 1), "sex": p.sex, **truth})
        if progress is not None:
            progress(len(verts), n_patients)
    log.info("accepted %d of %d candidates (%.0f %%)", n_patients, n_cand, 100 * n_patients / n_cand)
    ids = [r["ID"] for r in rows]
    return SyntheticCohort(ids, np.stack(verts), ref.faces, ref.landmarks, pd.DataFrame(rows), n_cand)
