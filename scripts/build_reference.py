"""Rebuild the vendored reference spine ``src/spinecohort/data/reference/reference_spine.npz`` from upstream.

Run (about 4 min on 2 cores; prints every check; writes the npz whose README lists the steps):

    git clone https://github.com/RemusR9/artisynth_lumbosacralSpineModel /tmp/remus
    pip download myo-sim==0.2.4 --no-deps -d /tmp/myo && unzip -q /tmp/myo/myo_sim-0.2.4-*.whl -d /tmp/myo
    python scripts/build_reference.py --remus-git /tmp/remus/.git --myo-models /tmp/myo/myo_sim/models

Upstream inputs (not vendored; pass their locations):

* ``--remus-git``: a git directory of github.com/RemusR9/artisynth_lumbosacralSpineModel (BSD-3; Visible
  Human Male geometry, Remus et al. 2021).  Read with ``git show HEAD:<path>``.
* ``--myo-models``: ``myo_sim/models`` of the PyPI wheel ``myo-sim`` 0.2.4 (Apache-2.0).

Steps (the data README lists them with the numbers this script prints):

1. Remus L1-L5, sacrum (S1), hip bones (Pelvis) and the body-only meshes (``*_body.obj``) and superior facet
   patches (``*_PDl_a`` / ``*_PDr_a``): metres -> mm; frame (+X anterior, +Y left, +Z superior) -> RAS
   (x = -Y, y = X, z = Z; +Y is the patient's left: the ``PDl`` (left) facet patches lie at +Y).
2. myo-sim thoracic meshes T1-T12, lumbar1 and femurs placed by their MuJoCo bodies
   (``scene/myobody_skeleton_decor.xml``); OpenSim frame (+X anterior, +Y up, +Z right) -> RAS axes, mm.
3. Thoracic levels: the Remus L1 remeshed at ``--edge-thoracic-template`` mm (the thoracic template, labeled by
   the same rules as L1) is moved onto each level by a smooth map in its body frame
   (:mod:`spinecohort.anatomy.level_map`): the body scaled to the level's published endplate width and depth
   and wedged to its anterior and posterior heights (:data:`BODY_ANCHORS`; narrowed anteriorly to a heart
   shape, :data:`TAPER_ANCHORS`; each scale corrected three times by
   the measured / asked ratio of :mod:`spinecohort.anatomy.morphometry`), the posterior elements scaled by
   :data:`ARCH_ANCHORS` and by the height of a motion segment, the articular pillars swirled about their
   vertical axes until the superior articular faces face posteriorly and laterally (:data:`FACET_FRONTAL_DEG`,
   :data:`FACET_PATCH_LAG_DEG`; a level whose map folds a triangle has its two joints' turns damped in
   5 deg steps), the spinous process turned and stretched onto the myo-sim level's spinous tip.  Every level keeps the
   template's vertex order and triangles, so the template's labels hold by index.  The level is placed by the
   myo-sim posture carried onto the Remus column: its body centre and axes are those of the myo-sim level
   under the similarity that takes myo-sim lumbar1's landmarks onto Remus L1's.
4. Femoral heads: the myo-sim femurs cut 45 mm below the head centre, smoothed (Loop subdivision) and
   placed with the head centre at the centre of the sphere fitted to the Remus acetabulum, scaled so the
   head radius is the acetabular radius minus ``--joint-space`` (cartilage gap); the head cap is then
   projected exactly onto that sphere.
5. Isotropic remeshing (ACVD) at ``--edge-vertebra`` / ``--edge-sacrum`` / ``--edge-pelvis`` /
   ``--edge-femur`` mm; the thoracic disc spaces set to ``--min-disc-mm`` (closest body-to-body distance),
   every overlapping joint separated; every part checked closed, manifold and free of self-intersections.
6. Labels and landmarks (:mod:`spinecohort.anatomy.labeling`) and the npz write.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spinecohort.anatomy import morphometry as M
from spinecohort.anatomy.assemble import BODY_TOLERANCE_MM, assemble, inside_or_near, label_vertebra
from spinecohort.anatomy.contacts import open_disc_spaces, push_out
from spinecohort.anatomy.labels import VERTEBRA_REGIONS, region_id
from spinecohort.anatomy.landmark_rules import similarity_from_points, vertebra_landmarks
from spinecohort.anatomy.level_map import LevelShape, Template, map_vertebra
from spinecohort.anatomy.reference import save_reference
from spinecohort.anatomy.surface import (
    check_surface,
    from_polydata,
    intersections_between,
    remesh_isotropic,
    self_intersections,
    sphere_fit,
    to_polydata,
)

REMUS_DIR = "hybrid_LSS_model/src/artisynth/models/passiveComponents_PlosOne/geometry/RB"
REMUS_TO_RAS = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
OSIM_TO_RAS = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def remus_mesh(git_dir: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    """One Remus OBJ in RAS mm."""
    text = subprocess.run(
        ["git", "-C", git_dir, "show", f"HEAD:{REMUS_DIR}/{name}.obj"], check=True, capture_output=True
    ).stdout
    tmp = Path("/tmp") / f"remus_{name}.obj"
    tmp.write_bytes(text)
    v, f = from_polydata(pv.read(tmp).triangulate().clean())
    return 1000.0 * v @ REMUS_TO_RAS.T, f


def myo_placements(models: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """mesh name -> (R (3, 3), t (3,) m) of every geom in the skeleton root frame (OpenSim axes).

    The bodies of this file carry positions only; the geoms carry ``pos`` and a rotation about the body z
    axis (``euler`` or ``quat``), which is all this reader accepts."""
    root = ET.parse(Path(models) / "scene" / "myobody_skeleton_decor.xml").getroot()
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def walk(body, origin):
        for child in body:
            if child.tag == "geom" and child.get("mesh"):
                pos = np.array([float(x) for x in child.get("pos", "0 0 0").split()])
                if child.get("quat"):
                    w, x, y, z = (float(a) for a in child.get("quat").split())
                    rot = Rotation.from_quat([x, y, z, w]).as_matrix()
                else:
                    ex, ey, ez = (float(a) for a in child.get("euler", "0 0 0").split())
                    if ex or ey:
                        raise ValueError(f"geom {child.get('mesh')}: only rotations about z are read")
                    rot = Rotation.from_euler("z", ez).as_matrix()
                out[child.get("mesh")] = (rot, origin + pos)
            elif child.tag == "body":
                pos = np.array([float(x) for x in child.get("pos", "0 0 0").split()])
                if child.get("quat") or (child.get("euler") and child.get("name") != "skeleton_decor_root"):
                    raise ValueError(f"body {child.get('name')}: rotated bodies are not read")
                walk(child, origin + (pos if child.get("name") != "skeleton_decor_root" else 0.0))

    walk(root, np.zeros(3))
    return out


def myo_mesh(models: str, name: str, placement=None) -> tuple[np.ndarray, np.ndarray]:
    """A myo-sim mesh in RAS axes, mm: in its own body frame, or placed (``placement`` = (R, t))."""
    v, f = from_polydata(pv.read(Path(models) / "meshes" / f"{name}.stl").clean())
    if placement is not None:
        rot, t = placement
        v = v @ rot.T + t
    return 1000.0 * v @ OSIM_TO_RAS.T, f


#: Published thoracic body dimensions the levels are built to (mm), as (level index k of Tk, value) anchors
#: interpolated linearly in k and held constant beyond the end anchors; every value is a row of
#: ``spinecohort/data/morphometry/panjabi.csv`` (its provenance there).
#: posterior body height: Panjabi 1991 text ("from 14.3 mm at T1 to 22.7 mm at T12", a steady rise);
#: anterior / posterior height ratio: Egwu 2019 T2 and T9, Kunkel 2011 T12; width: the mean of typical (T2-T9)
#: thoracic vertebrae placed at T5.5 (Indian dry bones, 200 vertebrae) and Panjabi 1991 Fig. 4A T11, T12;
#: depth: the same typical-thoracic mean, and at T12 the myo-sim T12 body box at the width scale.
BODY_ANCHORS = {
    "height_posterior": ((1.0, 14.3), (12.0, 22.7)),
    "height_ratio": ((2.0, 16.93 / 17.59), (9.0, 18.83 / 20.46), (12.0, 20.8 / 23.12)),
    "width": ((5.5, 27.02), (11.0, 35.2), (12.0, 39.2)),
    "depth": ((5.5, 20.78),),
}
#: Transverse scale of the posterior elements (canal, pedicle spacing) against L1: Panjabi's spinal canal
#: width of T11 and T12 over L1's (1991 Table 4, 1992), held constant above T11.
ARCH_ANCHORS = ((11.0, 19.4 / 23.7), (12.0, 22.2 / 23.7))
#: Narrowing of the body towards its anterior wall (level_map.LevelShape.taper): the heart-shaped outline of
#: the typical thoracic body.  A shape choice, not a published value (no table used here quantifies the
#: outline): a quarter at T3-T10, none at the transitional T1 and T12; the calibrated widths and depths do not
#: change with it.
TAPER_ANCHORS = ((1.0, 0.0), (3.0, 0.25), (10.0, 0.25), (12.0, 0.0))
#: Frontal angle (deg) of each level's superior articular face, in the convention of
#: :func:`spinecohort.anatomy.morphometry.facet_angles_deg` (the face's outward normal from posterior, positive
#: medially, negative laterally): T1-T11 face posteriorly and laterally, 25-30 deg from the frontal plane
#: (Masharawi 2004: 60-65 deg to the mid-sagittal plane; Gray's Anatomy: thoracic superior facets face
#: backwards, a little laterally and upwards), T12 faces medially, 26-34 deg to the mid-sagittal plane (the
#: thoracolumbar transition at T11-T12).  The articular processes are turned to the middle of each range.
FACET_FRONTAL_DEG = {**{f"T{k}": -27.5 for k in range(1, 12)}, "T12": 90.0 - 30.0}
#: How far (deg) the template's articular face (:func:`articular_faces`, on which the turn is computed) is
#: turned beyond its level's target: the contact patches (the process within 4 mm of its partner, found only
#: once the levels are placed and separated) reach into the swirl's fade and turn less.  With this lag the
#: reference's T2-T11 patches face 18-27 deg laterally (mean 21.6; a larger turn folds T1 and T2) and T12's
#: 59-62 deg medially (``tests/test_level_map.py``).
FACET_PATCH_LAG_DEG = {**{f"T{k}": -17.0 for k in range(1, 12)}, "T12": -8.0}
#: the step (deg) by which a turn that folds the surface is damped
FACET_DAMP_STEP_DEG = 5.0


def _interp(anchors, k: float) -> float:
    xs, ys = zip(*anchors)
    return float(np.interp(k, xs, ys))


def thoracic_template(tv, tf, t_body) -> tuple[Template, dict]:
    """The thoracic template (the remeshed Remus L1) in its morphometry frame (x right, y anterior, z
    superior), with its labels by the lumbar rules (:func:`spinecohort.anatomy.assemble.label_vertebra`)."""
    lab = label_vertebra(tv, tf, t_body)
    regions = {n: np.flatnonzero(lab["region"] == region_id(n)) for n in VERTEBRA_REGIONS}
    sup, inf = lab["rim_band_sup"], lab["rim_band_inf"]
    frame = M.vertebra_frame(tv, sup, inf, regions["body"], M.canal_centre(tv, regions))
    q = frame.local(tv)
    dims = M.body_dimensions(q, regions["body"], sup, inf)
    loc = q[:, [1, 0, 2]]
    body = regions["body"]
    mid = body[(np.abs(loc[body, 0]) < 4.0) & (np.abs(loc[body, 2]) < 8.0)]
    t = Template(
        loc,
        dims["endplate_width_upper"],
        dims["endplate_depth_upper"],
        dims["body_height_anterior"],
        dims["body_height_posterior"],
        float(loc[body, 1].max()),
        float(loc[mid, 1].min()),
        regions,
    )
    return t, {"frame": frame, "sup": sup, "inf": inf, "faces": tf}


def measure_local(t: Template, loc: np.ndarray, info: dict) -> dict:
    """Morphometry of a moved template given in the template's local axes."""
    parts = {k: v for k, v in t.regions.items() if len(v)}
    return M.measure_vertebra(loc[:, [1, 0, 2]], info["faces"], parts, info["sup"], info["inf"])


def fit_scales(t: Template, shape: LevelShape, info: dict, rounds: int = 3) -> LevelShape:
    """``shape`` with its body dimensions corrected ``rounds`` times by the ratio of the asked to the measured
    value (:mod:`spinecohort.anatomy.morphometry` on the mapped template), so the mapped level measures them."""
    want = {
        "endplate_width_upper": shape.width_mm,
        "endplate_depth_upper": shape.depth_mm,
        "body_height_anterior": shape.height_anterior_mm,
        "body_height_posterior": shape.height_posterior_mm,
    }
    names = ("width_mm", "depth_mm", "height_anterior_mm", "height_posterior_mm")
    asked = shape
    for _ in range(rounds):
        m = measure_local(t, map_vertebra(t, asked), info)
        asked = replace(asked, **{n: getattr(asked, n) * want[q] / m[q] for n, q in zip(names, want)})
    return asked


def articular_faces(t: Template, faces: np.ndarray) -> dict[str, np.ndarray]:
    """The template's superior articular faces: the vertices of each superior process whose outward normal
    points within 60 deg of the way to the inferior process of the same side in the transverse plane (where
    the inferior process of the level above lies when levels of this shape stack)."""
    from spinecohort.anatomy.labeling import vertex_normals

    n = vertex_normals(t.local, faces)
    out = {}
    for side in ("left", "right"):
        sup = t.regions[f"facet_sup_{side}"]
        to = t.local[t.regions[f"facet_inf_{side}"]].mean(0) - t.local[sup]
        to[:, 2] = 0.0
        to /= np.linalg.norm(to, axis=1, keepdims=True)
        out[side] = sup[np.sum(n[sup] * to, axis=1) > 0.5]
    return out


def face_frontal_deg(loc: np.ndarray, faces: np.ndarray, face: np.ndarray, side: float) -> float:
    """Frontal angle (deg, :func:`spinecohort.anatomy.morphometry.facet_facing`) of the articular face
    ``face`` of a mapped template ``loc`` (x right, y anterior, z superior); ``side`` -1 left, +1 right."""
    from spinecohort.anatomy.labeling import vertex_normals

    q = loc[:, [1, 0, 2]]
    return M.facet_facing(q[face], vertex_normals(q, faces)[face].sum(0), side)


def facet_turn(t: Template, shape: LevelShape, faces: np.ndarray, target_deg: float, rounds: int = 3) -> float:
    """The turn (deg, both processes alike) that brings the mean frontal angle of the mapped template's
    superior articular faces (:func:`articular_faces`) to ``target_deg``: the angle's error fed back
    ``rounds`` times (the swirl turns the face's outer part by less than the whole turn)."""
    face = articular_faces(t, faces)
    turn = 0.0
    for _ in range(rounds + 1):
        loc = map_vertebra(t, replace(shape, facet_sup_deg=turn, facet_inf_deg=turn))
        now = np.mean([face_frontal_deg(loc, faces, face[s], sg) for s, sg in (("left", -1.0), ("right", 1.0))])
        turn += now - target_deg
    return turn


def inf_turn(sup: dict[int, float], k: int) -> float:
    """The turn (deg) of level Tk's inferior processes: its partner's, the superior processes of T(k+1); none
    at T12 (its partner, L1, is not turned)."""
    return sup[k + 1] if k < 12 else 0.0


def thoracic_levels(args, tv, tf, t_body, l1_disc_mm, log):
    """T1..T12: the thoracic template (``tv``, ``tf``, body mask ``t_body``; the Remus L1 remeshed, in L1's
    place) moved by a per-level map (:mod:`spinecohort.anatomy.level_map`) to the published body dimensions,
    thoracic facet orientation and the myo-sim spinous process, then placed by the myo-sim posture carried
    onto the Remus column.  Every level keeps the template's vertex order and triangles.  ``l1_disc_mm``: the
    closest body-to-body distance L1-L2 of Remus."""
    place = myo_placements(args.myo_models)
    t, info = thoracic_template(tv, tf, t_body)
    src = vertebra_landmarks(tv)
    # the myo-sim posture carried onto Remus: similarity from myo lumbar1 (placed) to Remus L1
    lum_raw, _ = myo_mesh(args.myo_models, "lumbar1")
    lum_placed, _ = myo_mesh(args.myo_models, "lumbar1", place["lumbar1"])
    rl, _, tl = similarity_from_points(lum_raw, lum_placed, with_scale=False)  # same vertices: exact
    rot, scale, trans = similarity_from_points(vertebra_landmarks(lum_raw) @ rl.T + tl, src)
    log["myo_to_remus_scale"] = scale
    raws = {k: myo_mesh(args.myo_models, f"thoracic{k}_s")[0] for k in range(1, 13)}
    lmks = {k: vertebra_landmarks(raws[k]) for k in range(1, 13)}
    size = args.t12_body_width_mm / np.ptp(lmks[12][:8, 0])
    centres, rots = {}, {}
    for k in range(1, 13):
        name = f"thoracic{k}_s"
        placed, _ = myo_mesh(args.myo_models, name, place[name])
        rk, _, tk = similarity_from_points(raws[k], placed, with_scale=False)
        c_raw = 0.5 * (lmks[k][:8].min(0) + lmks[k][:8].max(0))  # body-box centre
        centres[k] = scale * (c_raw @ rk.T + tk) @ rot.T + trans
        rots[k] = rot @ rk
    depth_t12 = float(np.ptp(lmks[12][:8, 1]) * size)
    out, fits, turns = {}, {}, {}
    for k in range(1, 13):
        hp = _interp(BODY_ANCHORS["height_posterior"], k)
        arch_xy = _interp(ARCH_ANCHORS, k)
        # the arch spans a motion segment: its height follows the body height plus the disc (L1's: its
        # posterior height and its closest gap to L2)
        arch_z = (hp + args.min_disc_mm) / (t.height_posterior_mm + l1_disc_mm)
        c_box = 0.5 * (lmks[k][:8].min(0) + lmks[k][:8].max(0))
        tip = (lmks[k][8] - c_box) * size
        shape = LevelShape(
            width_mm=_interp(BODY_ANCHORS["width"], k),
            depth_mm=_interp(BODY_ANCHORS["depth"] + ((12.0, depth_t12),), k),
            height_anterior_mm=hp * _interp(BODY_ANCHORS["height_ratio"], k),
            height_posterior_mm=hp,
            arch_xyz=(arch_xy, arch_xy, arch_z),
            spinous_tip=(0.0, float(tip[1]), float(tip[2])),
            taper=_interp(TAPER_ANCHORS, k),
        )
        fits[k] = shape
        turns[k] = facet_turn(t, shape, tf, FACET_FRONTAL_DEG[f"T{k}"] + FACET_PATCH_LAG_DEG[f"T{k}"])
    # one turn for the thoracic joints T1-T2 ... T10-T11 (their mean), so that both processes of T1-T10 turn
    # alike; each inferior process turns with its partner, the superior process of the level below
    turn = float(np.mean([turns[k] for k in range(1, 12)]))
    sup = {**{k: turn for k in range(1, 12)}, 12: turns[12]}
    log["facet_turn_deg"] = {f"T{k}": turns[k] for k in range(1, 13)}
    fitted = {
        k: fit_scales(t, replace(fits[k], facet_sup_deg=sup[k], facet_inf_deg=inf_turn(sup, k)), info) for k in fits
    }
    # a level whose map folds a triangle has both its turns (its superior processes' joint and its inferior
    # processes' joint) damped in small steps, until no level folds; a joint's two processes keep one turn
    damp = dict.fromkeys(sup, 0.0)
    while True:
        damped = {k: float(np.sign(a) * max(abs(a) - damp[k], 0.0)) for k, a in sup.items()}
        trials = {k: replace(fitted[k], facet_sup_deg=damped[k], facet_inf_deg=inf_turn(damped, k)) for k in fitted}
        folding = [k for k in trials if self_intersections(map_vertebra(t, trials[k]), tf)]
        if not folding:
            break
        for k in folding:
            for j in (k, k + 1) if k < 12 else (k,):
                damp[j] = min(damp[j] + FACET_DAMP_STEP_DEG, abs(sup[j]))
    log["facet_damping_deg"] = {f"T{k}": damp[k] for k in damp}
    for k in range(1, 13):
        trial = trials[k]
        loc = map_vertebra(t, trial)
        if self_intersections(loc, tf):
            raise RuntimeError(f"T{k}: the fitted map folds the surface")
        log.setdefault("thoracic_shapes", {})[f"T{k}"] = asdict(trial)
        world = centres[k] + loc @ rots[k].T  # local axes = the myo-sim level's upright body axes
        out[f"T{k}"] = (world, tf.copy())
    log["thoracic_size_factor"] = size
    return out


def acetabulum_centre(points: np.ndarray, normals: np.ndarray, side: float) -> tuple[np.ndarray, float]:
    """Centre and radius of one acetabular cup (``side`` -1 left / +1 right) of the hip-bone surface.

    Hough vote: on a concave spherical cup every outward surface normal points at the centre, so the points
    ``p + r n`` for the right r pile up there; the densest pile over r = 20..32 mm seeds a sphere fit to the
    vertices that face it."""
    sel = np.flatnonzero(side * points[:, 0] > 40.0)
    p, n = points[sel], normals[sel]
    best = (-1, None)
    for r in np.arange(20.0, 32.5, 1.0):
        cand = p + r * n
        counts = np.array([len(x) for x in cKDTree(cand).query_ball_point(cand, 2.0)])
        k = int(np.argmax(counts))
        if counts[k] > best[0]:
            best = (int(counts[k]), cand[k])
    c = best[1]
    for _ in range(3):
        d = np.linalg.norm(c - p, axis=1)
        facing = np.sum(n * (c - p), axis=1) > 0.85 * d
        r_est = np.median(d[facing & (d < 35.0)])
        cup = facing & (np.abs(d - r_est) < 3.0)
        c, r = sphere_fit(p[cup])
    return c, r


def femoral_head(args, side: str, centre: np.ndarray, radius: float, log) -> tuple[np.ndarray, np.ndarray]:
    """Proximal femur (head, neck, trochanters) of myo-sim, its head made an exact sphere of ``radius`` at
    ``centre``; cut ``--femur-cut-mm`` below the head centre and closed."""
    place = myo_placements(args.myo_models)
    name = f"{'l' if side == 'L' else 'r'}_femur"
    v, f = myo_mesh(args.myo_models, name)  # femur body frame: origin at the hip-joint centre
    mesh = to_polydata(v, f).clip_closed_surface(normal=(0.0, 0.0, 1.0), origin=(0.0, 0.0, -args.femur_cut_mm))
    mesh = mesh.triangulate().clean().subdivide(2, "loop")
    v, f = from_polydata(mesh)
    lateral = 1.0 if side == "R" else -1.0
    cap0 = (np.linalg.norm(v, axis=1) < 26.0) & (v[:, 2] > -5.0) & (lateral * v[:, 0] < 5.0)
    c0, r0 = sphere_fit(v[cap0])
    v = (v - c0) * (radius / r0)
    v, f = remesh_isotropic(v, f, args.edge_femur)
    d = np.linalg.norm(v, axis=1)
    # the head cap: on the sphere within 1.5 mm and on the side away from the neck (the neck runs laterally)
    head = (np.abs(d - radius) < 1.5) & (v @ np.array([lateral, 0.0, -0.3]) < 0.35 * radius)
    v[head] *= (radius / d[head])[:, None]
    log[f"femur_{side}"] = {"myo_head_radius_mm": r0, "radius_mm": radius, "head_vertices": int(head.sum())}
    del place
    return v + centre, f, np.flatnonzero(head)


#: the largest rigid opening (mm) of a joint before the push-out is tried
MAX_RIGID_MM = 8.0


def separate_pair(
    parts: dict, followers: dict, column: list, upper: str, lower: str, gap_mm: float, max_push: int | None = None
) -> dict:
    """Separate two neighbouring vertebrae.  At growing rigid openings (the upper bone and all above it,
    ``column``, translated along the line between the two centroids in ``gap_mm`` steps, with the meshes in
    ``followers[level]``: label carriers, body and facet patches), push the articular surface of one bone out
    of the other (:func:`contacts.push_out`); the first opening at which the bones do not cross, or at which
    the push-out leaves no crossing, folds no triangle and moves at most ``max_push`` vertices, is kept."""
    crossings = intersections_between(*parts[upper], *parts[lower])
    axis = parts[upper][0].mean(0) - parts[lower][0].mean(0)
    axis /= np.linalg.norm(axis)
    shift = 0.0
    while True:
        left = intersections_between(*parts[upper], *parts[lower])
        if left == 0 and cKDTree(parts[lower][0]).query(parts[upper][0])[0].min() >= gap_mm:
            return {"crossings": crossings, "moved": f"{column[0]}-{upper}", "shift_mm": shift, "left": 0}
        for mover, fixed in ((upper, lower), (lower, upper)):
            va, left = push_out(parts[mover], parts[fixed], gap_mm)
            n = int(np.sum(np.any(va != parts[mover][0], axis=1)))
            if left == 0 and (max_push is None or n <= max_push) and self_intersections(va, parts[mover][1]) == 0:
                parts[mover] = (va, parts[mover][1])
                return {"crossings": crossings, "moved": mover, "vertices": n, "shift_mm": shift, "left": 0}
        if shift >= MAX_RIGID_MM:
            raise RuntimeError(f"{upper}-{lower}: still {left} crossings after a {shift} mm opening")
        shift += gap_mm
        for lv in column:
            parts[lv] = (parts[lv][0] + gap_mm * axis, parts[lv][1])
            for mesh in followers.get(lv, []):
                mesh += gap_mm * axis


def separate_bones(args, parts: dict, t_body: np.ndarray, bodies: dict, facets: dict, log: dict) -> None:
    """Close or open the thoracic disc spaces to ``--min-disc-mm``, then push every overlapping articular
    surface out of its partner (:mod:`spinecohort.anatomy.contacts`); parts are updated in place.
    ``t_body``: the body mask of the thoracic template (every thoracic level's vertex set)."""
    l1_body = inside_or_near(parts["L1"][0], *bodies["L1"], BODY_TOLERANCE_MM)
    column = [f"T{k}" for k in range(1, 13)] + ["L1"]
    masks = [t_body] * 12 + [l1_body]
    pts = [parts[lv][0].copy() for lv in column]
    log["thoracic_min_body_gap_mm"] = open_disc_spaces(pts, masks, args.min_disc_mm, close=True)
    for lv, p in zip(column, pts):
        parts[lv] = (p, parts[lv][1])
    names = column + ["L2", "L3", "L4", "L5", "S1"]
    followers: dict[str, list] = {}
    for lv in names[12:]:
        followers[lv] = [bodies[lv][0]] + [facets[f"{lv}_{s}"][0] for s in ("left", "right") if f"{lv}_{s}" in facets]
    moved = {}
    for k, (upper, lower) in enumerate(zip(names, names[1:])):
        # a warped thoracic level is only touched up by the push-out (its arch would lose its shape): the
        # rest of the overlap is opened rigidly
        cap = args.max_push_thoracic if upper.startswith("T") else None
        moved[f"{upper}-{lower}"] = separate_pair(
            parts, followers, names[: k + 1], upper, lower, args.joint_gap_mm, cap
        )
    for other in ("S1", "femur_L", "femur_R"):
        # the femoral-head cap stays an exact sphere: only the hip bone moves against a femur; at the
        # sacro-iliac joint the sacrum's auricular surface moves when the hip bone cannot be pushed out cleanly
        candidates = [("pelvis", other)] + ([(other, "pelvis")] if other == "S1" else [])
        for mover, fixed in candidates:
            va, left = push_out(parts[mover], parts[fixed], args.joint_gap_mm, max_rounds=12)
            folds = self_intersections(va, parts[mover][1])
            if left == 0 and folds == 0:
                break
        moved[f"pelvis-{other}"] = {
            "moved": mover,
            "vertices": int(np.sum(np.any(va != parts[mover][0], axis=1))),
            "left": left,
            "self_intersections": folds,
        }
        parts[mover] = (va, parts[mover][1])
    log["separation"] = moved
    for k, c in moved.items():
        print(f"separate {k:16s}", json.dumps(c), flush=True)


def pair_checks(parts: dict) -> dict:
    """Neighbouring bones: intersecting triangle pairs and the smallest vertex-to-vertex gap (mm)."""
    names = [f"T{k}" for k in range(1, 13)] + [f"L{k}" for k in range(1, 6)] + ["S1"]
    pairs = list(zip(names, names[1:])) + [("S1", "pelvis"), ("femur_L", "pelvis"), ("femur_R", "pelvis")]
    out = {}
    for a, b in pairs:
        gap = float(cKDTree(parts[a][0]).query(parts[b][0])[0].min())
        out[f"{a}-{b}"] = {"intersections": intersections_between(*parts[a], *parts[b]), "min_gap_mm": gap}
    return out


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--remus-git", required=True, help="git dir of RemusR9/artisynth_lumbosacralSpineModel")
    ap.add_argument("--myo-models", required=True, help="myo_sim/models of the unpacked myo-sim 0.2.4 wheel")
    ap.add_argument("--out", default="src/spinecohort/data/reference/reference_spine.npz")
    ap.add_argument("--edge-vertebra", type=float, default=2.2, help="target edge length on the vertebrae, mm")
    ap.add_argument(
        "--edge-thoracic-template", type=float, default=2.6, help="edge of the Remus L1 remesh the T levels map, mm"
    )
    ap.add_argument("--edge-sacrum", type=float, default=3.5)
    ap.add_argument("--edge-pelvis", type=float, default=5.0)
    ap.add_argument("--edge-femur", type=float, default=3.0)
    ap.add_argument(
        "--t12-body-width-mm",
        type=float,
        default=39.2,
        help="Panjabi 1991 T12 endplate width: the size of the myo-sim spinous tips and T12 depth",
    )
    ap.add_argument("--joint-space-mm", type=float, default=2.5, help="acetabular radius - head radius")
    ap.add_argument("--femur-cut-mm", type=float, default=45.0)
    ap.add_argument("--min-disc-mm", type=float, default=3.0, help="closest body-to-body distance, thoracic")
    ap.add_argument("--max-push-thoracic", type=int, default=400, help="most vertices a push moves at a T joint")
    ap.add_argument("--joint-gap-mm", type=float, default=0.5, help="clearance of pushed-apart joint surfaces")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    log: dict = {"args": vars(args)}
    parts: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    bodies: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for k in range(1, 6):
        v, f = remus_mesh(args.remus_git, f"L{k}_Schrumpfverpacken")
        parts[f"L{k}"] = remesh_isotropic(v, f, args.edge_vertebra)
        bodies[f"L{k}"] = remus_mesh(args.remus_git, f"L{k}_body")
    bodies["S1"] = remus_mesh(args.remus_git, "S1_body")
    facets = {
        f"{lv}_{s}": remus_mesh(args.remus_git, f"{lv}_PD{s[0]}_a")
        for lv in ("L2", "L3", "L4", "L5", "S1")
        for s in ("left", "right")
    }
    v, f = remus_mesh(args.remus_git, "L1_Schrumpfverpacken")
    template = remesh_isotropic(v, f, args.edge_thoracic_template)
    t_body = inside_or_near(template[0], *bodies["L1"], BODY_TOLERANCE_MM)
    l1_l2 = [
        p[0][inside_or_near(p[0], *bodies[lv], BODY_TOLERANCE_MM)]
        for lv, p in (("L1", parts["L1"]), ("L2", parts["L2"]))
    ]
    log["l1_l2_min_body_gap_mm"] = float(cKDTree(l1_l2[1]).query(l1_l2[0])[0].min())
    parts.update(thoracic_levels(args, *template, t_body, log["l1_l2_min_body_gap_mm"], log))
    v, f = remus_mesh(args.remus_git, "S1_Schrumpfverpacken")
    parts["S1"] = remesh_isotropic(v, f, args.edge_sacrum)
    v, f = remus_mesh(args.remus_git, "Pelvis")
    parts["pelvis"] = remesh_isotropic(v, f, args.edge_pelvis)
    from spinecohort.anatomy.labeling import vertex_normals

    pv_, pf_ = parts["pelvis"]
    heads = {}
    for side, sgn in (("L", -1.0), ("R", 1.0)):
        c, r = acetabulum_centre(pv_, vertex_normals(pv_, pf_), sgn)
        log[f"acetabulum_{side}"] = {"centre_mm": c.round(2).tolist(), "radius_mm": r}
        hv, hf, cap = femoral_head(args, side, c, r - args.joint_space_mm, log)
        parts[f"femur_{side}"] = (hv, hf)
        heads[side] = cap
    separate_bones(args, parts, t_body, bodies, facets, log)
    log["checks"] = {k: check_surface(*vf) for k, vf in parts.items()}
    for k, c in log["checks"].items():
        print(f"{k:9s}", json.dumps(c), flush=True)
    log["pairs"] = pair_checks(parts)
    for k, c in log["pairs"].items():
        print(f"{k:16s}", json.dumps(c), flush=True)
    ref = assemble(parts, (*template, t_body), bodies, facets, heads, log)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_reference(ref, out)
    print(f"wrote {out}: {len(ref.vertices)} vertices, {len(ref.faces)} triangles, {out.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
