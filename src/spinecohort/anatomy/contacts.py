"""Keep neighbouring bones of the reference apart: open thoracic disc spaces and congruent, non-overlapping
articular surfaces.

The Remus surfaces are shrink-wrapped bones posed in one frame; their facet joints and sacro-iliac joints
overlap by up to a few millimetres (the ArtiSynth model handles those contacts itself), and the placed
thoracic levels can overlap at the bodies.  Two steps remove every overlap:

1. :func:`open_disc_spaces`: from T12 upwards, each thoracic level and all above it are translated along the
   line joining the two body centres until the closest body-to-body distance is ``min_disc_mm``;
2. :func:`push_out`: the vertices of one bone that lie inside another, or closer than ``gap_mm`` to it, are
   moved to the other's surface plus ``gap_mm`` along the outward direction (the closest point of the fixed
   bone), repeated until the two surfaces no longer intersect: the moving articular surface becomes
   congruent with its partner at a joint space of ``gap_mm``.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from spinecohort.anatomy.surface import intersections_between, to_polydata


def open_disc_spaces(points: list[np.ndarray], body: list[np.ndarray], min_disc_mm: float) -> list[float]:
    """Translate levels in place so that consecutive bodies are ``min_disc_mm`` apart at their closest.

    points: vertebrae cranial to caudal, each (N_i, 3) mm (modified in place; the caudal-most one stays);
    body: their body-vertex masks.  Returns the shift of every level boundary (mm), cranial to caudal."""
    shifts = []
    for k in range(len(points) - 2, -1, -1):
        upper, lower = points[k][body[k]], points[k + 1][body[k + 1]]
        gap = float(cKDTree(lower).query(upper)[0].min())
        axis = upper.mean(0) - lower.mean(0)
        axis /= np.linalg.norm(axis)
        shift = max(0.0, min_disc_mm - gap)
        # the closest distance grows by at most the shift: iterate the few times it takes
        for _ in range(5):
            if shift <= 0:
                break
            for j in range(k + 1):
                points[j] += shift * axis
            gap = float(cKDTree(lower).query(points[k][body[k]])[0].min())
            shift = max(0.0, min_disc_mm - gap)
        shifts.append(gap)
    return shifts[::-1]


def _move_out(v: np.ndarray, fixed_mesh: pv.PolyData, clearance: float) -> int:
    """Move the vertices of ``v`` (in place) that are inside ``fixed_mesh`` or within ``clearance`` of it to
    its surface plus ``clearance``; returns how many moved."""
    d = np.asarray(pv.PolyData(v).compute_implicit_distance(fixed_mesh)["implicit_distance"])
    bad = np.flatnonzero(d < clearance)
    if len(bad) == 0:
        return 0
    _, closest = fixed_mesh.find_closest_cell(v[bad], return_closest_point=True)
    out = np.where((d[bad] < 0)[:, None], closest - v[bad], v[bad] - closest)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    ok = norm[:, 0] > 1e-9
    v[bad[ok]] = closest[ok] + clearance * out[ok] / norm[ok]
    return int(ok.sum())


def push_out(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], gap_mm: float, max_rounds: int = 8):
    """Vertices of ``a`` moved out of ``b``; the clearance starts at ``gap_mm`` and grows by half of it each
    round until no triangle pair crosses.  Returns the new vertices of a and the crossing pairs left."""
    va = a[0].copy()
    fixed = to_polydata(*b)
    left = intersections_between(va, a[1], *b)
    for r in range(max_rounds):
        if left == 0:
            break
        _move_out(va, fixed, gap_mm * (1.0 + 0.5 * r))
        left = intersections_between(va, a[1], *b)
    return va, left


def adjacent_contacts(vertices: np.ndarray, faces: np.ndarray, level: np.ndarray, region: np.ndarray) -> dict:
    """Crossing triangle pairs and closest vertex gap (mm) of every pair of neighbouring bones of one model in
    the reference topology: T1-T2 ... L5-S1 (the sacrum: regions sacrum and S1 plate), S1-pelvis and each
    femur against the hip bones.  ``level``/``region``: the reference's per-vertex labels."""
    from spinecohort.anatomy.labels import region_id

    sacrum = np.isin(region, [region_id("sacrum"), region_id("s1_plate")])
    bones = [level == i for i in range(int(level.max()) + 1)] + [sacrum]
    names = [f"level{i}" for i in range(int(level.max()) + 1)] + ["S1"]
    from spinecohort.cohort.landmarks import LEVELS

    names[: len(LEVELS)] = LEVELS
    hip = np.isin(region, [region_id("ilium"), region_id("pubis")])
    head = region == region_id("femoral_head")
    pairs = [(names[k], bones[k], names[k + 1], bones[k + 1]) for k in range(len(bones) - 1)]
    pairs += [("S1", sacrum, "pelvis", hip), ("femur_L", head & (vertices[:, 0] < 0), "pelvis", hip)]
    pairs += [("femur_R", head & (vertices[:, 0] > 0), "pelvis", hip)]
    out = {}
    for na, ma, nb, mb in pairs:
        fa, fb = faces[np.all(ma[faces], axis=1)], faces[np.all(mb[faces], axis=1)]
        gap = float(cKDTree(vertices[ma]).query(vertices[mb])[0].min())
        out[f"{na}-{nb}"] = {"crossings": intersections_between(vertices, fa, vertices, fb), "min_gap_mm": gap}
    return out
