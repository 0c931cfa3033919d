"""Mapping a hex body block onto a real vertebral body surface along rays, layer by layer and column by column.

The block is the template's O-grid body (node layers stacked between the two endplates).  Two ray maps, each
monotone along its rays, so neither can fold a layer or a column:

* in each node layer, the outer ring goes along its in-plane ray from the layer's centre to the body's wall
  (``R_wall / R_template``); the core block is scaled about the centre by the same ratio, interpolated by angle,
  and each ring node keeps its fraction of the straight line from its core-boundary node to its outer node, so a
  thin cortical ring stays a thin ring (:func:`in_plane_map`);
* each column of nodes (one O-grid node through all layers) moves along the body's axis so that its end nodes
  reach the endplates where a ray along the axis crosses them, the layers between following linearly
  (:func:`axial_map`): a concave endplate is followed node by node, without the sideways slide of a
  closest-point projection, which on a concave or partial endplate patch folds the layer under it.

The endplate layers take their outline from the wall a fixed depth (``rim_depth_mm``) inside the body: at the
rim the wall rounds into the endplate, and a ray in the endplate's own plane would cut that rounding.  Their rays
run in the layer's own plane (the endplate's fitted plane, tilted against the axis in a wedged body), shifted
along its normal (:func:`endplate_rays`), so the endplate's outline, hence the disc's cross-section, is the
bone's and the same whatever the number of layers.  The openings of the labeled body (where the pedicles leave
it) are closed first (:func:`closed_body`).
"""

from __future__ import annotations

import numpy as np

from spinecohort.mesh.vtk_mesh import surface

#: depth (mm) under the endplate's rim at which the wall gives the endplate layers their outline
RIM_DEPTH_MM = 2.0
#: ray-triangle pairs per chunk of the vectorised test (memory ~ chunk x 10 floats)
_CHUNK_PAIRS = 4_000_000


def _crossings(
    origins: np.ndarray, directions: np.ndarray, vertices: np.ndarray, faces: np.ndarray, farthest: bool
) -> np.ndarray:
    """(n,) distance along each ray to its farthest (or first) crossing of the triangles, inf where none."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    fill = -np.inf if farthest else np.inf
    out = np.full(len(directions), fill)
    step = max(1, _CHUNK_PAIRS // max(len(faces), 1))
    for lo in range(0, len(directions), step):
        d, o = directions[lo : lo + step], origins[lo : lo + step]
        s = o[:, None, :] - a[None]  # (n, T, 3)
        p = np.cross(d[:, None, :], e2[None])
        q = np.cross(s, e1[None])
        det = np.einsum("ntk,tk->nt", p, e1)
        ok = np.abs(det) > 1e-14
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        u = np.einsum("ntk,ntk->nt", p, s) * inv
        v = np.einsum("nk,ntk->nt", d, q) * inv
        t = np.einsum("tk,ntk->nt", e2, q) * inv
        hit = ok & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > 0)
        t = np.where(hit, t, fill)
        out[lo : lo + step] = t.max(axis=1) if farthest else t.min(axis=1)
    out[~np.isfinite(out)] = np.inf
    return out


def farthest_hits(origins: np.ndarray, directions: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) distance (in units of ``directions``) from each origin (n, 3) along its direction (n, 3) to the
    farthest crossing of the triangles (Moller-Trumbore, vectorised); ``inf`` where a ray crosses nothing.

    The farthest, not the first: from inside a body a ray leaves it once, and a ray that grazes a concave
    endplate's rim twice belongs to the outer crossing.
    """
    return _crossings(origins, directions, vertices, faces, farthest=True)


def first_hits(origins: np.ndarray, directions: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) distance along each ray (origins, unit directions (n, 3)) to the first crossing of the triangles ahead
    of it, ``inf`` where it crosses nothing (`farthest_hits`' test)."""
    return _crossings(origins, directions, vertices, faces, farthest=False)


def closed_body(vertices: np.ndarray, faces: np.ndarray, hole_size_mm: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """The labeled body surface with its openings (pedicle roots) closed: (vertices, triangles)."""
    mesh = surface(vertices, faces).fill_holes(hole_size_mm).triangulate().clean()
    return np.asarray(mesh.points, dtype=float), np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]


def _fill_missing(values: np.ndarray, positions: np.ndarray, k: int = 4) -> np.ndarray:
    """Values of rays that crossed nothing (a gap in the surface): the mean of the ``k`` nearest that did."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return values
    if bad.all():
        raise ValueError("no ray crosses the body surface: is the block inside its body?")
    from scipy.spatial import cKDTree

    good = np.flatnonzero(~bad)
    _, nn = cKDTree(positions[good]).query(positions[bad], k=min(k, len(good)))
    out = values.copy()
    out[bad] = values[good][nn.reshape(bad.sum(), -1)].mean(axis=1)
    return out


def _interp_periodic(angle: np.ndarray, at: np.ndarray, values: np.ndarray) -> np.ndarray:
    order = np.argsort(at)
    a, v = at[order], values[order]
    return np.interp(angle, np.r_[a[-1] - 2 * np.pi, a, a[0] + 2 * np.pi], np.r_[v[-1], v, v[0]])


def layer_normal(layer: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Unit normal (3,) of a planar node layer (n, 3) mm (total least squares), on the side of ``towards`` (3,)."""
    from spinecohort.anatomy.morphometry import plane_fit

    n = plane_fit(layer)[1]
    return n if n @ towards > 0 else -n


def endplate_rays(layer: np.ndarray, outer: np.ndarray, inward: np.ndarray, rim_depth_mm: float):
    """The rays that give an endplate layer (n2, 3) mm its outline: (origins (m, 3) mm, unit directions (m, 3),
    the outer nodes' distances (m,) mm from the layer's centre along them).  They run in the layer's own plane
    (the endplate's fitted plane, tilted against the body's axis where the body is a wedge), ``rim_depth_mm``
    inside the body along its normal (on the side of ``inward``), from the centre towards each outer node: the
    outline is the wall's at that depth, the same whatever the number of layers."""
    normal = layer_normal(layer, inward)
    rel = layer[outer] - layer.mean(0)
    rel -= (rel @ normal)[:, None] * normal
    r = np.linalg.norm(rel, axis=1)
    origins = np.tile(layer.mean(0) + rim_depth_mm * normal, (len(outer), 1))
    return origins, rel / r[:, None], r


def in_plane_map(
    block: np.ndarray, outer: np.ndarray, core_ids: np.ndarray, ring_line: tuple, body: tuple, rim_depth_mm: float
) -> np.ndarray:
    """Each node layer of ``block`` (nl, n2, 3) mm scaled in its plane along rays from its centre to the wall,
    the two endplate layers (first and last) to the wall ``rim_depth_mm`` inside the body (:func:`endplate_rays`;
    at least 0, under half the block's height).

    outer: (m,) outer-ring node ids; core_ids: ids of the core block's nodes; ring_line = (ring node ids,
    their core-boundary node, their outer node, their fraction along that line); body = (vertices, faces)."""
    nl = block.shape[0]
    centre = block.mean(axis=1)  # (nl, 3)
    axis = block[-1].mean(0) - block[0].mean(0)
    height = float(np.linalg.norm(axis))
    axis /= height
    if not 0.0 <= rim_depth_mm < height / 2:
        raise ValueError(
            f"rim depth {rim_depth_mm} mm: must be >= 0 and under half the body block's height {height:.2f} mm"
        )
    rel = block[:, outer] - centre[:, None]
    rel_plane = rel - (rel @ axis)[..., None] * axis
    r_tmpl = np.linalg.norm(rel_plane, axis=2)  # (nl, m)
    dirs = rel_plane / r_tmpl[..., None]
    origins = np.repeat(centre[:, None], len(outer), axis=1)
    ray_dirs, r_ray = dirs.copy(), r_tmpl.copy()
    for k, inward in ((0, axis), (nl - 1, -axis)):  # the endplate layers: rays in their own planes, under the rim
        origins[k], ray_dirs[k], r_ray[k] = endplate_rays(block[k], outer, inward, rim_depth_mm)
    hits = farthest_hits(origins.reshape(-1, 3), ray_dirs.reshape(-1, 3), *body)
    ratio = _fill_missing(hits / r_ray.ravel(), block[:, outer].reshape(-1, 3)).reshape(nl, -1)
    u = dirs[:, 0]  # a reference direction per layer for the angle about the axis
    out = block.copy()
    for k in range(nl):  # a handful of layers; every array operation inside is over the layer's nodes
        e1 = u[k] / np.linalg.norm(u[k])
        e2 = np.cross(axis, e1)
        ang_outer = np.arctan2(rel_plane[k] @ e2, rel_plane[k] @ e1)
        rc = block[k, core_ids] - centre[k]
        s_core = _interp_periodic(np.arctan2(rc @ e2, rc @ e1), ang_outer, ratio[k])
        rc_plane = rc - (rc @ axis)[:, None] * axis
        out[k, core_ids] = block[k, core_ids] + rc_plane * (s_core - 1.0)[:, None]
        out[k, outer] = block[k, outer] + rel_plane[k] * (ratio[k] - 1.0)[:, None]
    ids, start, end, frac = ring_line
    out[:, ids] = out[:, start] + frac[None, :, None] * (out[:, end] - out[:, start])
    return out


def axial_map(block: np.ndarray, outer: np.ndarray, inner: np.ndarray, body: tuple) -> np.ndarray:
    """Each column of ``block`` (nl, n2, 3) mm stretched along the block's axis so that its end nodes reach the
    endplates; the layers between move linearly.  The outer columns (``outer``, on the wall) take the offsets of
    the columns just inside them (``inner``): a ray along the wall would meet the rounded rim at an arbitrary
    height, and the thin outermost ring (cortex, outer annulus) would fold over that step."""
    nl = block.shape[0]
    axis = block[-1].mean(0) - block[0].mean(0)
    axis /= np.linalg.norm(axis)
    mid = block.mean(axis=0)  # (n2, 3): each column's mid point
    n = len(mid)
    up = farthest_hits(mid, np.tile(axis, (n, 1)), *body)
    down = farthest_hits(mid, np.tile(-axis, (n, 1)), *body)
    top = (mid - block[-1]) @ axis + _fill_missing(up, mid)
    bottom = (mid - block[0]) @ axis - _fill_missing(down, mid)
    top[outer], bottom[outer] = top[inner], bottom[inner]
    t = np.linspace(0.0, 1.0, nl)[:, None, None]
    return block + ((1 - t) * bottom[None, :, None] + t * top[None, :, None]) * axis


def plate_map(plate: np.ndarray, patch_vertices: np.ndarray, patch_faces: np.ndarray, depth_mm: float = 10.0):
    """A single node layer (1, n2, 3) mm moved along its normal onto an open endplate patch (the S1 plate):
    rays from ``depth_mm`` below each node, upwards; a node whose ray misses the patch takes its neighbours'
    offset."""
    layer = plate[0]
    c = layer.mean(0)
    n = np.linalg.svd(layer - c)[2][-1]
    n = n if n[2] > 0 else -n
    origins = layer - depth_mm * n
    hit = farthest_hits(origins, np.tile(n, (len(layer), 1)), patch_vertices, patch_faces)
    offset = _fill_missing(hit, origins) - depth_mm
    return (layer + offset[:, None] * n)[None]


def shared_outline(lower: np.ndarray, upper: np.ndarray, lower_share: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The two endplate layers (n2, 3) mm facing each other across a disc, each given the same in-plane shape
    about its own centre, ``lower_share`` of the lower's plus the rest of the upper's (heights along the disc's
    axis kept): the disc between them is then a prism, not a slab sheared by the difference of two outlines."""
    cl, cu = lower.mean(0), upper.mean(0)
    axis = cu - cl
    axis /= np.linalg.norm(axis)
    ol, ou = lower - cl, upper - cu
    hl, hu = ol @ axis, ou @ axis
    common = lower_share * (ol - hl[:, None] * axis) + (1.0 - lower_share) * (ou - hu[:, None] * axis)
    return cl + common + hl[:, None] * axis, cu + common + hu[:, None] * axis


def ring_lines(grid, cb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ring node ids, their core-boundary node, their outer node, their fraction along that line) of an O-grid
    (:class:`~spinecohort.mesh.template.OGrid`) with core-boundary node ids ``cb`` in ray order."""
    m = len(grid.outer)
    n_core = len(grid.nodes) - grid.shell_ring * m
    ring_ids = n_core + np.arange(grid.shell_ring * m)
    j = np.tile(np.arange(m), grid.shell_ring)
    start, end = cb[j], grid.outer[j]
    frac = np.linalg.norm(grid.nodes[ring_ids] - grid.nodes[start], axis=1) / np.linalg.norm(
        grid.nodes[end] - grid.nodes[start], axis=1
    )
    return ring_ids, start, end, frac
