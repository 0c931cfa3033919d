"""Closed triangulated surfaces built from rings of points (lofts), superellipsoids and tori.

Every function returns ``(vertices (V, 3) float64, faces (F, 3) int64)`` of a closed, manifold surface whose
triangles are oriented with outward normals, and whose vertex count and order depend only on the resolution
arguments.  That last property is what gives the synthetic cohort its vertex correspondence: two patients
built with the same resolution have the same vertex order, whatever their dimensions.

Written here rather than taken from pyvista/trimesh primitives because those do not expose the ring
structure the generator needs (endplate patches, wall rings for smooth noise weighting) and do not guarantee
a fixed vertex order across parameter values.
"""

from __future__ import annotations

import numpy as np


def superellipse_ring(a: float, b: float, n: int, exponent: float = 2.0) -> np.ndarray:
    """(n, 2) points of the superellipse |x/a|^p + |y/b|^p = 1, counter-clockwise from +x.

    ``n`` must be even so that the ring is centrally symmetric (point j and j + n/2 are opposite): the
    vertex mean and the area centroid of a cap triangulated from it are then exactly its centre.
    """
    if n % 2:
        raise ValueError(f"superellipse_ring needs an even point count, got {n}")
    phi = 2.0 * np.pi * np.arange(n) / n
    c, s = np.cos(phi), np.sin(phi)
    e = 2.0 / exponent
    return np.stack([a * np.sign(c) * np.abs(c) ** e, b * np.sign(s) * np.abs(s) ** e], axis=1)


def _grid_quads(first: int, n_rows: int, n_cols: int) -> np.ndarray:
    """Triangles joining ``n_rows`` consecutive periodic rows of ``n_cols`` vertices, outward for
    counter-clockwise rows stacked in the direction of the outward-facing cross product."""
    r = np.arange(n_rows - 1)[:, None]
    j = np.arange(n_cols)[None, :]
    a = first + r * n_cols + j
    b = first + r * n_cols + (j + 1) % n_cols
    c = b + n_cols
    d = a + n_cols
    tri = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], axis=1)
    return tri.reshape(-1, 3)


def closed_loft(
    rings: np.ndarray,
    bottom_apex: np.ndarray | None = None,
    top_apex: np.ndarray | None = None,
    bottom_cap_rings: int = 0,
    top_cap_rings: int = 0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Close a stack of rings into a surface.

    rings: (R, T, 3), ordered from bottom to top, each ring counter-clockwise when seen from the top
        (so that the wall normals point outward).
    *_apex: a point closing that end with a triangle fan (e.g. a superellipsoid pole).  When None, the end
        is closed by a planar cap: ``*_cap_rings`` inner rings shrunk towards the ring's vertex mean, then a
        fan to that centre.  A planar end ring thus gives a planar, centrally symmetric patch.

    Returns vertices, faces and ``info`` with index arrays ``wall`` (R, T), ``bottom_cap`` / ``top_cap``
    (all vertices of each cap patch, rim included) and ``bottom_rim`` / ``top_rim``.
    """
    rings = np.asarray(rings, dtype=float)
    n_r, n_t, _ = rings.shape
    verts = [rings.reshape(-1, 3)]
    faces = [_grid_quads(0, n_r, n_t)]
    wall = np.arange(n_r * n_t).reshape(n_r, n_t)
    info: dict = {"wall": wall, "bottom_rim": wall[0], "top_rim": wall[-1]}
    count = n_r * n_t

    for end in ("bottom", "top"):
        rim_idx = wall[0] if end == "bottom" else wall[-1]
        rim = rings[0] if end == "bottom" else rings[-1]
        apex = bottom_apex if end == "bottom" else top_apex
        n_inner = bottom_cap_rings if end == "bottom" else top_cap_rings
        if apex is None:
            centre = rim.mean(axis=0)
            scales = 1.0 - np.arange(1, n_inner + 1) / (n_inner + 1.0)
            inner = centre + scales[:, None, None] * (rim - centre)[None]
            apex_pt = centre
        else:
            inner = np.zeros((0, n_t, 3))
            apex_pt = np.asarray(apex, dtype=float)
        inner_idx = count + np.arange(inner.shape[0] * n_t).reshape(-1, n_t)
        verts.append(inner.reshape(-1, 3))
        count += inner.shape[0] * n_t
        apex_idx = count
        verts.append(apex_pt[None])
        count += 1
        # Rows from the rim inwards; the last row fans to the apex.
        rows = [rim_idx] + list(inner_idx)
        tris = []
        for outer, inn in zip(rows[:-1], rows[1:]):
            a, b = outer, np.roll(outer, -1)
            c, d = np.roll(inn, -1), inn
            tris.append(np.stack([a, b, c], -1))
            tris.append(np.stack([a, c, d], -1))
        last = rows[-1]
        tris.append(np.stack([last, np.roll(last, -1), np.full(n_t, apex_idx)], -1))
        cap = np.concatenate(tris)
        if end == "bottom":
            cap = cap[:, ::-1]  # seen from below, the rings run clockwise
        faces.append(cap)
        info[f"{end}_cap"] = np.concatenate([rim_idx, inner_idx.ravel(), [apex_idx]]).astype(np.int64)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int64), info


def frame_points(local: np.ndarray, rotation: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Map local coordinates (..., 3) into the world: ``origin + rotation @ local``."""
    return np.asarray(origin) + np.asarray(local) @ np.asarray(rotation).T


def superellipsoid(
    centre: np.ndarray,
    rotation: np.ndarray,
    semi_axes: tuple[float, float, float],
    n_theta: int = 16,
    n_rings: int = 9,
    exponent: float = 2.5,
) -> tuple[np.ndarray, np.ndarray]:
    """A closed rounded-box superellipsoid; local z is the pole axis, semi_axes = (x, y, z) half lengths mm."""
    ax, ay, az = semi_axes
    # Ring heights spaced in angle so the poles are well sampled.
    v = np.linspace(-np.pi / 2, np.pi / 2, n_rings + 2)[1:-1]
    e = 2.0 / exponent
    cv, sv = np.cos(v), np.sin(v)
    ring2d = superellipse_ring(1.0, 1.0, n_theta, exponent)
    radial = np.abs(cv) ** e
    z = az * np.sign(sv) * np.abs(sv) ** e
    local = np.empty((n_rings, n_theta, 3))
    local[..., 0] = ax * radial[:, None] * ring2d[None, :, 0]
    local[..., 1] = ay * radial[:, None] * ring2d[None, :, 1]
    local[..., 2] = z[:, None]
    rings = frame_points(local, rotation, centre)
    verts, faces, _ = closed_loft(
        rings,
        bottom_apex=frame_points(np.array([0.0, 0.0, -az]), rotation, centre),
        top_apex=frame_points(np.array([0.0, 0.0, az]), rotation, centre),
    )
    return verts, faces


def segment_superellipsoid(
    p0: np.ndarray,
    p1: np.ndarray,
    half_width: float,
    half_thickness: float,
    up_hint: np.ndarray,
    n_theta: int = 16,
    n_rings: int = 9,
    exponent: float = 2.5,
) -> tuple[np.ndarray, np.ndarray]:
    """A superellipsoid spanning the segment p0-p1 (a process, pedicle, ramus ...).

    ``half_width`` lies along the component of ``up_hint`` perpendicular to the segment, ``half_thickness``
    along the third axis.  Its ends reach ``half_thickness`` beyond p0 and p1 so the rounded tip covers them.
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    if length <= 0:
        raise ValueError("segment_superellipsoid needs two distinct points")
    ez = axis / length
    up = np.asarray(up_hint, float) - np.dot(up_hint, ez) * ez
    if np.linalg.norm(up) < 1e-9:
        up = np.cross(ez, [1.0, 0.0, 0.0])
        if np.linalg.norm(up) < 1e-9:
            up = np.cross(ez, [0.0, 1.0, 0.0])
    ey = up / np.linalg.norm(up)
    ex = np.cross(ey, ez)
    rot = np.stack([ex, ey, ez], axis=1)
    return superellipsoid(
        0.5 * (p0 + p1),
        rot,
        (half_thickness, half_width, 0.5 * length + half_thickness),
        n_theta,
        n_rings,
        exponent,
    )


def uv_sphere(centre: np.ndarray, radius: float, n_theta: int = 32, n_rings: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """A closed sphere of ``radius`` mm whose every vertex lies exactly on the sphere."""
    return superellipsoid(centre, np.eye(3), (radius, radius, radius), n_theta, n_rings, exponent=2.0)


def torus(
    centre: np.ndarray, axis: np.ndarray, major_radius: float, minor_radius: float, n_major: int = 32, n_minor: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus around ``axis`` through ``centre`` (e.g. the acetabular rim around a femoral head)."""
    ez = np.asarray(axis, float) / np.linalg.norm(axis)
    tmp = np.array([1.0, 0.0, 0.0]) if abs(ez[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ex = np.cross(tmp, ez)
    ex /= np.linalg.norm(ex)
    ey = np.cross(ez, ex)
    u = 2 * np.pi * np.arange(n_major) / n_major
    v = 2 * np.pi * np.arange(n_minor) / n_minor
    radial = major_radius + minor_radius * np.cos(v)[None, :]
    pts = (
        np.asarray(centre, float)
        + (radial * np.cos(u)[:, None])[..., None] * ex
        + (radial * np.sin(u)[:, None])[..., None] * ey
        + (minor_radius * np.sin(v)[None, :] * np.ones((n_major, 1)))[..., None] * ez
    )
    verts = pts.reshape(-1, 3)
    i = np.arange(n_major)[:, None]
    j = np.arange(n_minor)[None, :]
    a = i * n_minor + j
    b = ((i + 1) % n_major) * n_minor + j
    c = ((i + 1) % n_major) * n_minor + (j + 1) % n_minor
    d = i * n_minor + (j + 1) % n_minor
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], axis=1).reshape(-1, 3)
    return verts, faces.astype(np.int64)


def edge_check(faces: np.ndarray) -> tuple[bool, bool]:
    """(closed and manifold, consistently oriented): every undirected edge in exactly two faces, and every
    directed edge exactly once (its neighbour runs it the other way)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    und = np.sort(e, axis=1)
    _, counts = np.unique(und, axis=0, return_counts=True)
    manifold = bool(np.all(counts == 2))
    _, dcounts = np.unique(e, axis=0, return_counts=True)
    oriented = manifold and bool(np.all(dcounts == 1))
    return manifold, oriented


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume in mm^3 (positive for outward-oriented closed surfaces)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
