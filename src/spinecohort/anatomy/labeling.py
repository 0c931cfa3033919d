"""Automatic labels of a vertebra surface, by geometric rules in the vertebra's own frame.

Frame: x to the patient's right, y anterior, z up (mm), the vertebra upright.  Inputs are one vertebra's
vertices, vertex normals (outward, unit) and its landmark points (:func:`landmark_rules.vertebra_landmarks`);
the vertebral body is given (the Remus ``*_body`` surfaces, or labels carried by correspondence).

Regions of the posterior elements: every non-body vertex goes to its nearest seed (Euclidean), seeds per
region: spinous = its tip and two points on the line from the tip to the lamina midline; transverse = tip and
the midpoint tip-pedicle; superior / inferior articular process = its tip; pedicle = a point behind the body's
posterior wall at mid-height, 55 % of the body half-width off the midline; lamina = the midline point of the
arch and the midpoints between the articular tips on each side.

Endplates: body vertices whose normal points cranially (``n . z > 0.6``) in the upper half of the body form
the superior endplate (caudally, lower half: the inferior one).  The **rim** is the band of endplate vertices
within ``rim_mm`` of the endplate's outer edge (the ring apophysis); the endplate **plane** used for every
angle is the least-squares plane of the rim band: the plane through the anterior and posterior corners that a
radiographic endplate line joins, unaffected by the central concavity.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from spinecohort.anatomy.labels import region_id

#: an endplate vertex lies within this distance of the patch's least-squares plane (the central concavity of
#: a lumbar endplate is 1-3 mm deep)
PLANE_TOLERANCE_MM = 4.0


def posterior_regions(points: np.ndarray, is_body: np.ndarray, lmk: np.ndarray) -> np.ndarray:
    """(N,) region label of every vertex of one vertebra (body where ``is_body``)."""
    corners, tips = lmk[:8], lmk[8:]
    spin, tp_l, tp_r, sap_l, sap_r, iap_l, iap_r = tips
    x_l, x_r = corners[:, 0].min(), corners[:, 0].max()
    y_post = corners[:, 1].min()
    z_mid = 0.5 * (corners[:, 2].min() + corners[:, 2].max())
    half = 0.5 * (x_r - x_l)
    ped_l = np.array([-0.55 * half, y_post - 4.0, z_mid])
    ped_r = np.array([0.55 * half, y_post - 4.0, z_mid])
    lam_l, lam_r = 0.5 * (sap_l + iap_l), 0.5 * (sap_r + iap_r)
    lam_mid = np.array([0.0, 0.5 * (lam_l[1] + lam_r[1]) - 4.0, 0.5 * (lam_l[2] + lam_r[2])])
    seeds = [
        (spin, "spinous"),
        (spin + (lam_mid - spin) / 3.0, "spinous"),
        (spin + 2.0 * (lam_mid - spin) / 3.0, "spinous"),
        (tp_l, "transverse_left"),
        (0.5 * (tp_l + ped_l), "transverse_left"),
        (tp_r, "transverse_right"),
        (0.5 * (tp_r + ped_r), "transverse_right"),
        (sap_l, "facet_sup_left"),
        (sap_r, "facet_sup_right"),
        (iap_l, "facet_inf_left"),
        (iap_r, "facet_inf_right"),
        (ped_l, "pedicle_left"),
        (ped_r, "pedicle_right"),
        (lam_mid, "lamina"),
        (lam_l + 0.3 * (lam_mid - lam_l), "lamina"),
        (lam_r + 0.3 * (lam_mid - lam_r), "lamina"),
    ]
    seed_pts = np.array([s for s, _ in seeds])
    seed_lab = np.array([region_id(n) for _, n in seeds])
    out = seed_lab[cKDTree(seed_pts).query(points)[1]]
    out[is_body] = region_id("body")
    return out.astype(np.int8)


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) area-weighted outward unit vertex normals of a closed, consistently oriented surface."""
    fn = np.cross(points[faces[:, 1]] - points[faces[:, 0]], points[faces[:, 2]] - points[faces[:, 0]])
    n = np.zeros_like(points)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
    if np.sum(n * (points - points.mean(0))) < 0:  # inward-oriented input
        n = -n
    return n


def boundary_band(patch: np.ndarray, faces: np.ndarray, points: np.ndarray, width_mm: float) -> np.ndarray:
    """Vertices of ``patch`` (indices) within ``width_mm`` of its boundary (vertices of the patch with a
    neighbour outside it): the outer band of an endplate."""
    inside = np.zeros(len(points), bool)
    inside[patch] = True
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    cut = inside[edges[:, 0]] != inside[edges[:, 1]]
    edge_v = np.unique(edges[cut].ravel())
    edge_v = edge_v[inside[edge_v]]
    d = cKDTree(points[edge_v]).query(points[patch])[0]
    return patch[d <= width_mm], edge_v


def endplates(points, normals, faces, is_body, rim_mm: float = 3.0) -> dict[str, np.ndarray]:
    """Superior / inferior endplate patches, their rim bands and outer edges (vertex indices) of one body."""
    body = np.flatnonzero(is_body)
    z = points[body, 2]
    z_mid = 0.5 * (z.min() + z.max())
    out = {}
    for key, sign in (("sup", 1.0), ("inf", -1.0)):
        sel = body[(sign * normals[body, 2] > 0.6) & (sign * (points[body, 2] - z_mid) > 0)]
        # drop vertices off the endplate's plane (the pedicle bases and the wall's lip also face cranially or
        # caudally), then keep the largest connected patch
        for _ in range(3):
            p = points[sel]
            normal = np.linalg.svd(p - p.mean(0))[2][-1]
            sel = sel[np.abs((p - p.mean(0)) @ normal) < PLANE_TOLERANCE_MM]
        out[f"endplate_{key}"] = _largest_component(sel, faces)
        band, edge = boundary_band(out[f"endplate_{key}"], faces, points, rim_mm)
        out[f"rim_band_{key}"] = band
        out[f"rim_{key}"] = edge
    return out


def _largest_component(sel: np.ndarray, faces: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    inside = np.zeros(faces.max() + 1, bool)
    inside[sel] = True
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = edges[inside[edges[:, 0]] & inside[edges[:, 1]]]
    n = len(inside)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    best = np.bincount(comp[sel]).argmax()
    return sel[comp[sel] == best]
