"""Synthetic thoracolumbar spine cohort with ground-truth spinopelvic parameters.

Patient data cannot be shared, so the embedded default input is generated.  Each patient is a triangulated
surface model of T1-L5 (vertebral bodies with planar endplates; posterior arch with pedicles, laminae,
spinous, transverse and articular processes), the sacrum with the S1 endplate, the pelvis (iliac wings,
acetabular rims, pubic and ischial rami) and both femoral heads, in millimetres, frame RAS (x right,
y anterior, z up).

How the ground truth is known: the generator *places* the geometry on the alignment chain of
:mod:`spinecohort.cohort.alignment`.  The pelvis is built around the hip axis
with the S1 plate at pelvic incidence PI, then rotated about the hip axis by the pelvic tilt PT; the column
is stacked from S1 upwards by prescribing the sagittal and coronal tilt of every endplate (normal
``normalize(tan cor, tan sag, 1)``) and the central height of every disc and body.  Every true parameter is
a sum of imposed angles or an angle of imposed positions, computed here in the construction frame
(V = +z, A = +y) without any plane or sphere fit, i.e. independently of :mod:`spinecohort.measure.spinopelvic`.

Correspondence: every patient is built from the same primitives at the same resolution, so vertex count,
vertex order and faces are identical across patients (as bi-planar X-ray reconstructions give).  Vertices are
numbered in order of first use by the face list, so an STL written and read back (merging vertices in
first-occurrence order) returns the same point order.

Smooth shape noise (random Gaussian bumps) perturbs the posterior elements, the pelvis, the sacrum below its
plate and the vertebral-body walls (weighted by sin(pi t) along the body height) but never the endplate
patches or femoral heads, so the imposed endplate planes and head spheres stay exact.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation, Slerp

from spinecohort.cohort.alignment import (  # noqa: F401  (re-exported: the generator's public names)
    BODY_HALF_DEPTH,
    BODY_HALF_WIDTH,
    BODY_HEIGHT,
    CRITERIA,
    DISC_HEIGHT,
    ENDPLATE_EXPONENT,
    LEVEL_IDX,
    N_POS,
    S1_HALF_DEPTH,
    S1_HALF_WIDTH,
    Chain,
    PatientParameters,
    build_chain,
    coronal_endplate_tilts,
    draw_patient,
    endplate_frame,
    endplate_normal,
    level_interp,
    meets_criteria,
    pos_inf,
    pos_sup,
    rot_x,
    sagittal_joint_angles,
    true_parameters,
)
from spinecohort.cohort.landmarks import LEVELS, Landmarks
from spinecohort.cohort.surfaces import closed_loft, segment_superellipsoid, superellipse_ring, torus, uv_sphere

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Resolution:
    """Point counts of the primitives; the total vertex count per patient follows from them."""

    body_theta: int = 64  # points around a vertebral body / endplate rim (even)
    body_wall_rings: int = 14  # rings up the body wall, endplate rims included
    body_cap_rings: int = 6  # inner rings of each endplate patch
    part_theta: int = 20  # points around a posterior-element / pelvis primitive
    part_rings: int = 11
    pelvis_theta: int = 32
    pelvis_rings: int = 17
    sacrum_theta: int = 64
    sacrum_rings: int = 30
    head_theta: int = 48
    head_rings: int = 23


RESOLUTIONS: dict[str, Resolution] = {
    "coarse": Resolution(24, 6, 3, 10, 5, 14, 7, 24, 12, 20, 9),
    "default": Resolution(),
    "fine": Resolution(128, 28, 12, 40, 21, 64, 33, 128, 60, 96, 47),
}

# ----------------------------------------------------------------------------------------------------------
# Mesh assembly


@dataclass
class _Builder:
    """Accumulates closed components with part labels, noise weights and landmark index sets."""

    part_names: list[str] = field(default_factory=list)
    verts: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    labels: list[np.ndarray] = field(default_factory=list)
    weights: list[np.ndarray] = field(default_factory=list)
    count: int = 0
    sets: dict = field(default_factory=dict)
    anchors: dict = field(default_factory=dict)

    def add(self, part: str, verts: np.ndarray, faces: np.ndarray, weight: np.ndarray | float = 1.0) -> int:
        if part not in self.part_names:
            self.part_names.append(part)
        start = self.count
        self.verts.append(verts)
        self.faces.append(faces + start)
        self.labels.append(np.full(len(verts), self.part_names.index(part), np.int16))
        self.weights.append(np.broadcast_to(np.asarray(weight, float), (len(verts),)).copy())
        self.count += len(verts)
        return start


def _body(b: _Builder, level: int, chain: Chain, scale: float, res: Resolution) -> None:
    lv = LEVELS[level]
    bottom, top = pos_inf(level), pos_sup(level)
    ring = superellipse_ring(
        BODY_HALF_WIDTH[level] * scale, BODY_HALF_DEPTH[level] * scale, res.body_theta, ENDPLATE_EXPONENT
    )
    t = np.linspace(0.0, 1.0, res.body_wall_rings)
    rots = Slerp([0.0, 1.0], Rotation.from_matrix(chain.frames[[bottom, top]]))(t).as_matrix()
    centres = chain.centres[bottom] + t[:, None] * (chain.centres[top] - chain.centres[bottom])
    waist = 1.0 - 0.07 * np.sin(np.pi * t)  # bodies are narrower at mid-height
    local = np.concatenate([ring[None] * waist[:, None, None], np.zeros((len(t), len(ring), 1))], axis=2)
    rings = centres[:, None, :] + np.einsum("rij,rtj->rti", rots, local)
    v, f, info = closed_loft(rings, bottom_cap_rings=res.body_cap_rings, top_cap_rings=res.body_cap_rings)
    w = np.zeros(len(v))
    w[info["wall"].ravel()] = np.repeat(np.sin(np.pi * t), len(ring))
    s = b.add(f"body_{lv}", v, f, w)
    b.sets.setdefault("endplate_inf", {})[lv] = s + info["bottom_cap"]
    b.sets.setdefault("endplate_sup", {})[lv] = s + info["top_cap"]
    b.sets.setdefault("rim_inf", {})[lv] = s + info["bottom_rim"]
    b.sets.setdefault("rim_sup", {})[lv] = s + info["top_rim"]
    b.sets.setdefault("body", {})[lv] = s + np.arange(len(v))


def _posterior(b: _Builder, level: int, chain: Chain, scale: float, res: Resolution) -> None:
    """Pedicles, laminae, spinous and transverse processes, articular processes of one vertebra."""
    lv = LEVELS[level]
    i = float(level)
    bottom, top = pos_inf(level), pos_sup(level)
    centre = 0.5 * (chain.centres[bottom] + chain.centres[top])
    rot = Slerp([0.0, 1.0], Rotation.from_matrix(chain.frames[[bottom, top]]))(0.5).as_matrix()
    lumbar = level >= 12
    s = scale
    bd = BODY_HALF_DEPTH[level] * s
    h = BODY_HEIGHT[level] * s
    cw = level_interp((8.0, 9.0, 12.0), i) * s  # canal half width
    cd = level_interp((14.0, 15.0, 16.0), i) * s  # canal depth
    pr = level_interp((3.0, 4.0, 5.5), i) * s  # pedicle radius
    pl = level_interp((9.0, 10.0, 12.0), i) * s
    sl = level_interp((38.0, 35.0, 30.0), i) * s
    sh = level_interp((4.0, 7.0, 12.0), i) * s
    tl = level_interp((22.0, 12.0, 18.0), i) * s
    incl = np.radians(np.interp(i, [0, 7, 11, 16], [35, 60, 30, 10]))
    up = np.array([0.0, 0.0, 1.0])
    ant = np.array([0.0, 1.0, 0.0])
    xp = cw + pr
    yl = -bd - pl  # pedicle-lamina junction
    ys = yl - 0.8 * cd  # lamina junction at the midline
    spin_end = np.array([0.0, ys - sl * np.cos(incl), -1.0 - sl * np.sin(incl)])
    parts = [
        # (p0, p1, half_width, half_thickness, up_hint) in the vertebra's mid-height frame
        ((np.array([0.0, ys, -1.0]), spin_end, sh, 2.8, up)),
    ]
    for sgn in (-1.0, 1.0):
        parts += [
            (np.array([sgn * xp, -bd + 1.0, 0.0]), np.array([sgn * xp, yl, 0.0]), 1.4 * pr, pr, up),
            (np.array([sgn * xp, yl, 0.0]), np.array([0.0, ys, -1.0]), 0.45 * h, 2.5, up),
            (
                np.array([sgn * xp, yl, 1.0]),
                np.array([sgn * (xp + tl), yl - (0.1 if lumbar else 0.35) * tl, 3.0]),
                4.0 * s,
                3.0 * s,
                up,
            ),
            (
                np.array([sgn * xp, yl - 1.0, 0.3 * h]),
                np.array([sgn * xp, yl - 3.0, 0.5 * h + 6.0 * s]),
                4.0 * s,
                3.0 * s,
                ant,
            ),
            (
                np.array([sgn * (xp - 1.0), yl - 0.4 * cd, -0.3 * h]),
                np.array([sgn * (xp - 1.0), yl - 0.4 * cd - 2.0, -0.5 * h - 6.0 * s]),
                4.0 * s,
                3.0 * s,
                ant,
            ),
        ]
    names = ["spinous"] + [f"{k}_{side}" for side in "LR" for k in ("pedicle", "lamina", "tp", "sap", "iap")]
    n_ring = res.part_rings * res.part_theta
    mid_ring = (res.part_rings // 2) * res.part_theta
    for name, (p0, p1, hw, ht, hint) in zip(names, parts):
        v, f = segment_superellipsoid(p0, p1, hw, ht, hint, res.part_theta, res.part_rings)
        start = b.add(f"posterior_{lv}", centre + v @ rot.T, f, 1.0)
        # Ligament anchors by topology (identical for every patient): the apexes sit at p0 / p1, the
        # mid ring's vertices at theta = 90 / 270 deg lie on the +/- up_hint side of the segment.
        top_apex, mid_up, mid_down = (
            start + n_ring + 1,
            start + mid_ring + res.part_theta // 4,
            start + mid_ring + 3 * res.part_theta // 4,
        )
        a = b.anchors
        if name == "spinous":
            a.setdefault("spinous_tip", {})[lv] = top_apex
            a.setdefault("spinous_upper", {})[lv] = mid_up
            a.setdefault("spinous_lower", {})[lv] = mid_down
        elif name.startswith("lamina"):
            a.setdefault(f"lamina_upper_{name[-1]}", {})[lv] = mid_up
            a.setdefault(f"lamina_lower_{name[-1]}", {})[lv] = mid_down
        elif name[:3] in ("tp_", "sap", "iap"):
            a.setdefault(f"{name[:-2]}_tip_{name[-1]}", {})[lv] = top_apex


def _sacrum(b: _Builder, p: PatientParameters, chain: Chain, res: Resolution) -> None:
    """Lofted sacrum: S1 plate on top, alae just below it, curving anteriorly to the apex."""
    s = p.scale
    frame, c0 = chain.frames[0], chain.centres[0]
    ex, ey, ez = frame[:, 0], frame[:, 1], frame[:, 2]
    arc_knots = np.array([0.0, 2.5, 15.0, 35.0, 55.0, 75.0, 95.0]) * s
    a_knots = np.array([S1_HALF_WIDTH, 54.0, 52.0, 42.0, 30.0, 20.0, 10.0]) * s
    b_knots = np.array([S1_HALF_DEPTH, 24.0, 26.0, 22.0, 15.0, 10.0, 6.0]) * s
    arc = np.concatenate([arc_knots[:2], np.linspace(arc_knots[2], arc_knots[-1], res.sacrum_rings - 2)])
    kappa = np.radians(50.0) / (105.0 * s)
    ks = kappa * arc
    centre = c0 - (np.sin(ks) / kappa)[:, None] * ez + ((1 - np.cos(ks)) / kappa)[:, None] * ey
    ring_y = np.cos(ks)[:, None] * ey + np.sin(ks)[:, None] * ez
    a = np.interp(arc, arc_knots, a_knots)
    bb = np.interp(arc, arc_knots, b_knots)
    unit = superellipse_ring(1.0, 1.0, res.sacrum_theta, ENDPLATE_EXPONENT)
    rings = (
        centre[:, None, :]
        + (a[:, None] * unit[None, :, 0])[..., None] * ex
        + (bb[:, None] * unit[None, :, 1])[..., None] * ring_y[:, None, :]
    )
    rings = rings[::-1]  # bottom (apex end) first, S1 plate last
    apex_arc = 105.0 * s
    apex = c0 - np.sin(kappa * apex_arc) / kappa * ez + (1 - np.cos(kappa * apex_arc)) / kappa * ey
    v, f, info = closed_loft(rings, bottom_apex=apex, top_cap_rings=res.body_cap_rings)
    w = np.ones(len(v))
    w[info["top_cap"]] = 0.0
    w[info["wall"][-2:].ravel()] = 0.0  # the plate's rim and the alae shoulder stay exact
    start = b.add("sacrum", v, f, w)
    b.sets.setdefault("endplate_sup", {})["S1"] = start + info["top_cap"]
    b.sets.setdefault("rim_sup", {})["S1"] = start + info["top_rim"]


def _pelvis(b: _Builder, p: PatientParameters, res: Resolution) -> None:
    """Hemipelves built around the hip axis (origin) in the PT = 0 orientation, then tilted by PT."""
    s, w, r = p.scale, 0.5 * p.hip_width, p.fh_radius
    rot = rot_x(p.PT)
    up = np.array([0.0, 0.0, 1.0])
    symphysis = []
    for sgn in (-1.0, 1.0):
        head = np.array([sgn * w, 0.0, 0.0])
        axis = np.array([sgn * 1.0, 0.3, -0.55])
        axis /= np.linalg.norm(axis)
        minor = 4.5 * s
        offset = 0.35 * r
        major = np.sqrt((r + minor + 1.0) ** 2 - offset**2)
        v, f = torus(head + offset * axis, axis, major, minor, 2 * res.pelvis_theta, max(res.part_theta // 2, 6))
        b.add("pelvis", v @ rot.T, f)
        segs = [
            # superior pubic ramus from the symphysis (p0) to the acetabulum: its first rings are the
            # symphysis patch
            ((sgn * 6 * s, 58 * s, -28 * s), (sgn * (w - 12 * s), 22 * s, -5 * s), 8 * s, 6 * s, up),
            ((sgn * 6 * s, 55 * s, -45 * s), (sgn * (w - 25 * s), -10 * s, -62 * s), 9 * s, 6 * s, up),
            ((sgn * (w - 25 * s), -10 * s, -62 * s), (sgn * (w - 8 * s), -15 * s, -20 * s), 10 * s, 8 * s, up),
            (
                (sgn * (w - 2 * s), -8 * s, r + 6 * s),
                (sgn * (w + 8 * s), -20 * s, 70 * s),
                14 * s,
                9 * s,
                np.array([0.0, 1.0, 0.0]),
            ),
            (
                (sgn * 55 * s, -35 * s, 105 * s),
                (sgn * (w + 35 * s), 45 * s, 90 * s),
                28 * s,
                4.5 * s,
                np.array([sgn * 0.5, 0.0, 1.0]),
            ),
        ]
        for k, (p0, p1, hw, ht, hint) in enumerate(segs):
            v, f = segment_superellipsoid(np.array(p0), np.array(p1), hw, ht, hint, res.pelvis_theta, res.pelvis_rings)
            start = b.add("pelvis", v @ rot.T, f)
            if k == 0:
                # bottom apex (index n_rings * n_theta) and the first ring sit at the symphyseal end
                n = res.pelvis_rings * res.pelvis_theta
                symphysis.append(start + np.concatenate([np.arange(res.pelvis_theta), [n]]))
    b.sets["pubic_symphysis"] = np.concatenate(symphysis)


def build_patient_mesh(
    p: PatientParameters,
    res: Resolution,
    noise_mm: float = 0.8,
    noise_width_mm: float = 25.0,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray, Landmarks, dict]:
    """Vertices (N, 3) mm in the patient's own (placed) frame, faces (F, 3), landmarks, ground truth."""
    chain = build_chain(p)
    b = _Builder()
    for level in range(len(LEVELS)):
        _body(b, level, chain, p.scale, res)
    for level in range(len(LEVELS)):
        _posterior(b, level, chain, p.scale, res)
    _sacrum(b, p, chain, res)
    _pelvis(b, p, res)
    fh = {}
    for side, sgn in (("L", -1.0), ("R", 1.0)):
        v, f = uv_sphere(np.array([sgn * 0.5 * p.hip_width, 0.0, 0.0]), p.fh_radius, res.head_theta, res.head_rings)
        start = b.add(f"femoral_head_{side}", v, f, 0.0)
        fh[side] = start + np.arange(len(v))
    verts = np.concatenate(b.verts)
    faces = np.concatenate(b.faces)
    weights = np.concatenate(b.weights)
    truth = true_parameters(p, chain, verts[b.sets["rim_sup"]["S1"]])

    if rng is not None and noise_mm > 0:
        verts = verts + weights[:, None] * smooth_noise(verts, rng, noise_mm, noise_width_mm)

    # Rigid placement: rotation about the vertical and translation keep every parameter unchanged.
    placement = Rotation.from_euler("z", p.axial_rotation_deg, degrees=True).as_matrix()
    verts = verts @ placement.T + p.translation

    # Number vertices by first use in the face list so that an STL round trip preserves the order.
    order = first_use_order(faces, len(verts))
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    verts = verts[order]
    faces = inverse[faces]
    part = np.concatenate(b.labels)[order]

    def remap(idx):
        return np.sort(inverse[idx])

    lm = Landmarks(
        part=part,
        part_names=tuple(b.part_names),
        endplate_sup={k: remap(v) for k, v in b.sets["endplate_sup"].items()},
        endplate_inf={k: remap(v) for k, v in b.sets["endplate_inf"].items()},
        rim_sup={k: remap(v) for k, v in b.sets["rim_sup"].items()},
        rim_inf={k: remap(v) for k, v in b.sets["rim_inf"].items()},
        femoral_head={k: remap(v) for k, v in fh.items()},
        body={k: remap(v) for k, v in b.sets["body"].items()},
        pubic_symphysis=remap(b.sets["pubic_symphysis"]),
        meta={"generator": "spinecohort.cohort.synthetic", "resolution": asdict(res)},
        anchors={k: inverse[np.array([v[lv] for lv in LEVELS])] for k, v in b.anchors.items()},
    )
    return verts, faces, lm, truth


def first_use_order(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Vertex indices in order of their first appearance in ``faces.ravel()``; all must appear."""
    flat = faces.ravel()
    uniq, first = np.unique(flat, return_index=True)
    if len(uniq) != n_vertices:
        raise ValueError(f"{n_vertices - len(uniq)} vertices are used by no face")
    return uniq[np.argsort(first)]


def smooth_noise(
    points: np.ndarray, rng: np.random.Generator, amplitude_mm: float, width_mm: float, n_bumps: int = 60
) -> np.ndarray:
    """A smooth random displacement field: Gaussian bumps with random centres and vector amplitudes."""
    lo, hi = points.min(0), points.max(0)
    centres = rng.uniform(lo, hi, size=(n_bumps, 3))
    amps = rng.normal(0.0, amplitude_mm, size=(n_bumps, 3))
    out = np.zeros_like(points)
    for c, a in zip(centres, amps):  # 60 bumps: a loop over bumps, each one array operation over points
        out += np.exp(-np.sum((points - c) ** 2, axis=1) / (2 * width_mm**2))[:, None] * a
    return out


@dataclass
class SyntheticCohort:
    ids: list[str]
    vertices: np.ndarray  # (P, N, 3)
    faces: np.ndarray  # (F, 3)
    landmarks: Landmarks
    table: pd.DataFrame  # one row per patient: ID, age, sex, true parameters
    n_candidates: int


def generate_cohort(
    n_patients: int = 42,
    seed: int = 20240549,
    resolution: str | Resolution = "default",
    noise_mm: float = 0.8,
    criteria: dict = CRITERIA,
    max_candidates: int = 100000,
    progress=None,
) -> SyntheticCohort:
    """Draw patients until ``n_patients`` meet the inclusion criteria; build their meshes."""
    res = RESOLUTIONS[resolution] if isinstance(resolution, str) else resolution
    rng = np.random.default_rng(seed)
    accepted: list[tuple[PatientParameters, np.random.Generator]] = []
    n_cand = 0
    while len(accepted) < n_patients:
        if n_cand >= max_candidates:
            raise RuntimeError(f"only {len(accepted)} of {max_candidates} candidates met the criteria {criteria}")
        n_cand += 1
        p = draw_patient(rng, f"P{len(accepted) + 1:02d}")
        truth = true_parameters(p, build_chain(p), _s1_rim_only(p))
        if meets_criteria(truth, criteria):
            accepted.append((p, np.random.default_rng(rng.integers(2**63))))
    verts, rows, faces0, lm0 = [], [], None, None
    for k, (p, noise_rng) in enumerate(accepted):
        v, f, lm, truth = build_patient_mesh(p, res, noise_mm=noise_mm, rng=noise_rng)
        if faces0 is None:
            faces0, lm0 = f, lm
        elif not np.array_equal(f, faces0):
            raise AssertionError("generator broke correspondence: faces differ between patients")
        verts.append(v)
        rows.append({"ID": p.ID, "age": round(p.age, 1), "sex": p.sex, **truth})
        if progress is not None:
            progress(k + 1, len(accepted))
    table = pd.DataFrame(rows)
    log.info("accepted %d of %d candidates (%.0f %%)", n_patients, n_cand, 100 * n_patients / n_cand)
    return SyntheticCohort([p.ID for p, _ in accepted], np.stack(verts), faces0, lm0, table, n_cand)


def _s1_rim_only(p: PatientParameters) -> np.ndarray:
    """The S1 plate rim of a candidate without building its mesh (for the inclusion check)."""
    chain = build_chain(p)
    ring = superellipse_ring(S1_HALF_WIDTH * p.scale, S1_HALF_DEPTH * p.scale, 64, ENDPLATE_EXPONENT)
    return chain.centres[0] + np.c_[ring, np.zeros(len(ring))] @ chain.frames[0].T
