"""Facet joints from the bones' own articular surfaces: the contact plane, the part of the two surfaces that
face each other, the contact points spread over it and the bone-to-bone gap, on a model's own coordinates.

A joint is the inferior articular surface (IAP) of the upper vertebra and the superior one (SAP) of the lower
(the template's ``sites``, `spinecohort.mesh.ligament_sites`).  Its contact normal is the mean of the two
surfaces' total-least-squares plane normals, pointing from the SAP towards the IAP (the direction in which the
SAP pushes the IAP).  The two surfaces are projected on the plane; the facing part is where each surface has the
other within `FACING_MM` of it in projection; `contact_points` spreads ``n`` points over it (k-means in the
plane, deterministic start), and at each the gap is the IAP's height minus the SAP's along the normal (heights
of the nearest projected nodes).  Units: mm, degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a node of one surface faces the other when a node of the other lies within this distance (mm) of it in the
#: contact plane's projection (the template's skin spacing is ~1-2 mm)
FACING_MM = 2.0


@dataclass(frozen=True)
class JointGeometry:
    """One facet joint on a model: centre (3,) mm of the facing part, normal (3,) unit SAP -> IAP, contact
    points (n, 3) mm midway between the two surfaces, gaps (n,) mm bone-to-bone along the normal at each
    (negative: the surfaces overlap), facing_area_mm2 of the facing part's projection (its convex hull)."""

    centre: np.ndarray
    normal: np.ndarray
    points: np.ndarray
    gaps: np.ndarray
    facing_area_mm2: float


def plane_normal(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and unit normal (3,) of the total-least-squares plane of `points` (P, 3) mm (the right
    singular vector of the smallest singular value; sign arbitrary)."""
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[2]


def in_plane_axes(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal in-plane axes of a plane with unit `normal`."""
    a = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def kmeans_points(xy: np.ndarray, n: int, iterations: int = 30) -> np.ndarray:
    """(n, 2) centres of `n` clusters of the points `xy` (P, 2), Lloyd's iterations from a farthest-point start
    (deterministic): contact points spread evenly over the facing part."""
    n = min(n, len(xy))
    start = [int(np.argmin(np.linalg.norm(xy - xy.mean(0), axis=1)))]
    dist = np.linalg.norm(xy - xy[start[0]], axis=1)
    for _ in range(n - 1):
        start.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(xy - xy[start[-1]], axis=1))
    centres = xy[start] if n > 1 else xy.mean(0, keepdims=True)
    for _ in range(iterations if n > 1 else 0):
        label = np.argmin(((xy[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)
        centres = np.stack([xy[label == k].mean(0) if np.any(label == k) else centres[k] for k in range(n)])
    return centres


def joint_geometry(
    sap: np.ndarray,
    iap: np.ndarray,
    n_points: int,
    sap_outward: np.ndarray | None = None,
    iap_outward: np.ndarray | None = None,
    facing_mm: float = FACING_MM,
) -> JointGeometry:
    """The joint between the SAP surface nodes `sap` (S, 3) mm of the lower vertebra and the IAP surface nodes
    `iap` (I, 3) of the upper (module docstring).  The normal is the mean of the two surfaces' own plane normals,
    each turned to point SAP -> IAP by the surface's outward side (`sap_outward`, `iap_outward`: its skin
    triangles' normal; None: the side of the other surface's centroid).  One plane through both surfaces is the
    same where they face each other, and wrong where the two patches lie side by side (T11-T12 of the real mean,
    whose patches are ~7 x 3.5 mm: its normal came out 135-141 deg from cranial).  Where fewer than 3 nodes face
    the other surface the contact points spread over both surfaces."""
    from scipy.spatial import ConvexHull, cKDTree  # here: the shard jobs import this module, never call it

    _, n_s = plane_normal(sap)
    _, n_i = plane_normal(iap)
    towards = iap.mean(0) - sap.mean(0)
    n_s = n_s if n_s @ (towards if sap_outward is None else sap_outward) >= 0 else -n_s
    n_i = n_i if n_i @ (towards if iap_outward is None else -iap_outward) >= 0 else -n_i
    normal = (n_s + n_i) / np.linalg.norm(n_s + n_i)
    centre = np.concatenate([sap, iap]).mean(0)
    axes = in_plane_axes(normal)
    xy_s, xy_i = (sap - centre) @ axes.T, (iap - centre) @ axes.T
    h_s, h_i = (sap - centre) @ normal, (iap - centre) @ normal
    d_si, _ = cKDTree(xy_i).query(xy_s)
    d_is, _ = cKDTree(xy_s).query(xy_i)
    facing = np.concatenate([xy_s[d_si <= facing_mm], xy_i[d_is <= facing_mm]])
    if len(facing) < 3:
        facing = np.concatenate([xy_s, xy_i])
    xy = kmeans_points(facing, n_points)
    _, js = cKDTree(xy_s).query(xy)
    _, ji = cKDTree(xy_i).query(xy)
    mid = 0.5 * (h_s[js] + h_i[ji])
    pts = centre + xy @ axes + mid[:, None] * normal
    area = float(ConvexHull(facing).volume)
    return JointGeometry(centre + facing.mean(0) @ axes, normal, pts, h_i[ji] - h_s[js], area)
