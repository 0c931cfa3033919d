"""Keep neighbouring bones of the reference apart: open thoracic disc spaces and congruent, non-overlapping
articular surfaces.

The Remus surfaces are shrink-wrapped bones posed in one frame; their facet joints and sacro-iliac joints
overlap by up to a few millimetres (the ArtiSynth model handles those contacts itself), and the placed
thoracic levels can overlap at the bodies.  Two steps remove every overlap:

1. :func:`open_disc_spaces`: from T12 upwards, each thoracic level and all above it are translated along the
   line joining the two body centres until the closest body-to-body distance is ``min_disc_mm`` (the build
   also closes wider spaces to it);
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


def open_disc_spaces(
    points: list[np.ndarray], body: list[np.ndarray], min_disc_mm: float, close: bool = False
) -> list[float]:
    """Translate levels in place so that consecutive bodies are ``min_disc_mm`` apart at their closest (with
    ``close`` also moving bodies farther apart than that towards each other).

    points: vertebrae cranial to caudal, each (N_i, 3) mm (modified in place; the caudal-most one stays);
    body: their body-vertex masks.  Returns the closest body-to-body distance of every joint (mm), cranial
    to caudal."""
    lowest = -np.inf if close else 0.0
    shifts = []
    for k in range(len(points) - 2, -1, -1):
        upper, lower = points[k][body[k]], points[k + 1][body[k + 1]]
        gap = float(cKDTree(lower).query(upper)[0].min())
        axis = upper.mean(0) - lower.mean(0)
        axis /= np.linalg.norm(axis)
        shift = max(lowest, min_disc_mm - gap)
        # the closest distance changes by at most the shift: iterate the few times it takes
        for _ in range(5):
            if abs(shift) < 1e-3:
                break
            for j in range(k + 1):
                points[j] += shift * axis
            gap = float(cKDTree(lower).query(points[k][body[k]])[0].min())
            shift = max(lowest, min_disc_mm - gap)
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


def bone_pairs(level: np.ndarray, region: np.ndarray, x: np.ndarray, faces: np.ndarray) -> list[tuple]:
    """The neighbouring bones of a model in the reference topology: T1-T2 ... L5-S1 (the sacrum: regions sacrum
    and S1 plate), S1-pelvis and each femur against the hip bones.  ``level``/``region``: the reference's
    per-vertex labels; ``x``: the reference's x coordinates (the femur side).  Returns (name, vertex indices
    of a, faces of a, vertex indices of b, faces of b) per pair, the faces numbered into their bone's indices."""
    from spinecohort.anatomy.labels import region_id
    from spinecohort.cohort.landmarks import LEVELS

    sacrum = np.isin(region, [region_id("sacrum"), region_id("s1_plate")])
    hip = np.isin(region, [region_id("ilium"), region_id("pubis")])
    head = region == region_id("femoral_head")
    bones = [(lv, level == i) for i, lv in enumerate(LEVELS)] + [("S1", sacrum)]
    pairs = [(*bones[k], *bones[k + 1]) for k in range(len(bones) - 1)]
    pairs += [("S1", sacrum, "pelvis", hip), ("femur_L", head & (x < 0), "pelvis", hip)]
    pairs += [("femur_R", head & (x > 0), "pelvis", hip)]
    out = []
    for na, ma, nb, mb in pairs:
        out.append((f"{na}-{nb}", *_local(ma, faces), *_local(mb, faces)))
    return out


def _local(mask: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertex indices of a bone and its faces renumbered into them."""
    idx = np.flatnonzero(mask)
    new = np.full(len(mask), -1)
    new[idx] = np.arange(len(idx))
    return idx, new[faces[np.all(mask[faces], axis=1)]]


def pair_contact(vertices: np.ndarray, pair: tuple) -> tuple[int, float]:
    """Crossing triangle pairs (VTK OBB-tree collision test) and closest vertex-to-vertex gap (mm) of one pair
    of :func:`bone_pairs`.

    Only the triangles near the other bone are tested: two crossing triangles share a point within the longest
    edge of a vertex of each, so a triangle none of whose vertices is within the sum of the two bones' longest
    edges of the other bone cannot cross it."""
    _, ia, fa, ib, fb = pair
    va, vb = vertices[ia], vertices[ib]
    margin = _longest_edge(va, fa) + _longest_edge(vb, fb)
    da = cKDTree(vb).query(va, distance_upper_bound=margin)[0]
    db = cKDTree(va).query(vb, distance_upper_bound=margin)[0]
    near_a, near_b = fa[np.any(da[fa] < margin, axis=1)], fb[np.any(db[fb] < margin, axis=1)]
    gap = float(min(da.min(), db.min()))
    if len(near_a) == 0 or len(near_b) == 0:
        return 0, gap if np.isfinite(gap) else float(cKDTree(va).query(vb)[0].min())
    return intersections_between(va, near_a, vb, near_b), gap


def _longest_edge(v: np.ndarray, f: np.ndarray) -> float:
    return float(np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).max())


def adjacent_contacts(vertices: np.ndarray, faces: np.ndarray, level: np.ndarray, region: np.ndarray) -> dict:
    """Crossing triangle pairs and closest vertex gap (mm) of every pair of neighbouring bones of one model in
    the reference topology (:func:`bone_pairs`)."""
    out = {}
    for pair in bone_pairs(level, region, vertices[:, 0], faces):
        n, gap = pair_contact(vertices, pair)
        out[pair[0]] = {"crossings": n, "min_gap_mm": gap}
    return out


def cohort_contacts(vertices: np.ndarray, faces: np.ndarray, level: np.ndarray, region: np.ndarray):
    """Per neighbouring-bone pair over a cohort (P, N, 3) in the reference topology: patients with crossing
    triangles, the most crossing pairs in one patient and the closest vertex gap (mm) of any patient."""
    import pandas as pd

    pairs = bone_pairs(level, region, vertices[0, :, 0], faces)
    res = np.array([[pair_contact(v, pair) for pair in pairs] for v in vertices])  # (P, pairs, 2)
    return pd.DataFrame(
        {
            "patients_crossing": (res[:, :, 0] > 0).sum(0),
            "max_crossings": res[:, :, 0].max(0).astype(int),
            "min_gap_mm": res[:, :, 1].min(0),
        },
        index=[p[0] for p in pairs],
    )
