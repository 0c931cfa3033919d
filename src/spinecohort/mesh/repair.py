"""Local untangling of inverted hexahedra in a morphed sample (reference: hex-quality.md section 3.3).

A sample X = mean + sum w_i mode_i can fold elements. We repair only a patch around the bad elements:

1. bad elements: scaled Jacobian <= target (tau = 0.05, or half the element's reference value if that is lower)
   or not certified valid by the Bernstein check;
2. patch: nodes of the bad elements grown by r node rings; surface nodes (nodes of faces owned by one hex) are
   fixed, or slide in their tangent plane in the escalation steps (surface feature nodes, where face normals
   differ by > 30 deg, stay fixed); patch elements = all elements touching a movable node;
3. minimise over the movable nodes a target-matrix Winslow energy with a modified determinant (Garanzha et al.
   2021 "Foldover-free maps in 50 lines of code"; Escobar et al. 2003), measured against the valid mean mesh:
   per corner and centre of each patch element T = A W^-1 (A: sample edge vectors, W: the same in the mean mesh),
   f(T) = |T|_F^2 / (3 chi^(2/3)) + lam (det^2 T + 1) / (2 chi),  chi(d, eps) = (d + sqrt(d^2 + eps^2)) / 2,
   plus mu |x - x0|^2 / h^2 per movable node (h: mean reference edge length). Analytic gradient, scipy L-BFGS-B;
   outer loop eps = sqrt(1e-8 + 0.04 min(det T, 0)^2) until the patch is above target;
4. escalation r = 1 -> 2 -> 2 sliding -> 3 sliding, each from the input, stopping at the first step that leaves no
   element below target (straight to sliding if a fold involves only surface nodes); if every step leaves an
   invalid element, the widest step once more with the feature nodes sliding too (a fold pinned at a rim). The
   best step is returned if every element of the mesh is then certified valid (Bernstein); otherwise RepairError.

Written here because no Python library untangles hex meshes with a fixed/sliding boundary (Mesquite and the
gmsh WinslowUntangler are C++). Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from spinecohort.mesh.quality.certificate import certify_valid
from spinecohort.mesh.quality.element import CORNER_NEIGHBOURS, HEX_EDGES, HEX_FACES, check_mesh
from spinecohort.mesh.quality.kernels import min_scaled_jacobian_nb
from spinecohort.mesh.quality.verdict import corner_jacobians

# scipy.optimize, scipy.sparse and pyvista are imported where they are used: a shard job imports this module
# for the few models that need untangling (none on the default grid) and would pay ~0.5 s for them per job
if TYPE_CHECKING:
    import pyvista as pv
    import scipy.sparse


class RepairError(ValueError):
    """The mesh could not be untangled by any escalation step."""


@dataclass
class RepairReport:
    invalid_before: int  # elements with scaled Jacobian <= 0 or not certified
    invalid_after: int
    bad_before: int  # elements below target (includes invalid)
    min_scaled_jacobian_before: float
    min_scaled_jacobian_after: float
    moved_nodes: np.ndarray  # node ids whose position changed (sparse correction: ids + displacement_mm)
    max_displacement_mm: float
    displacement_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (n_moved, 3)
    patch_rings: int = 0
    sliding: bool = False
    attempts: list[str] = field(default_factory=list)

    @property
    def n_nodes_moved(self) -> int:
        return int(len(self.moved_nodes))


@dataclass(frozen=True)
class UntangleContext:
    """Everything untangle needs that depends only on the connectivity and the reference (mean) mesh."""

    sj_reference: np.ndarray  # (E,) scaled Jacobian of the reference mesh
    faces: np.ndarray  # (F, 4) boundary quads
    is_boundary: np.ndarray  # (N,) surface node
    feature: np.ndarray  # (N,) surface node on an edge/corner of the reference surface: never moves
    reference_face_normals: np.ndarray  # (F, 3)
    incidence: scipy.sparse.csr_matrix  # (E, N) element-node incidence


def prepare_untangle(
    hexes: np.ndarray, reference_points: np.ndarray, feature_angle_deg: float = 30.0
) -> UntangleContext:
    """Precompute the topology and reference quality for ``untangle``; raises ValueError if the reference is invalid."""
    ref, hexes = check_mesh(reference_points, hexes)
    if ref.ndim != 2:
        raise ValueError(f"reference_points must be (n_nodes, 3), got {ref.shape}")
    sj_ref, invalid_ref, _ = _bad_elements(ref, hexes, np.zeros(len(hexes)))
    if invalid_ref.any():
        raise ValueError(
            f"reference mesh has {invalid_ref.sum()} invalid elements, e.g. {np.flatnonzero(invalid_ref)[:5].tolist()}"
        )
    faces = boundary_faces(hexes)
    is_boundary = np.zeros(len(ref), bool)
    is_boundary[faces.ravel()] = True
    ref_face = _quad_normals(ref, faces)
    feature = _node_normals(ref_face, faces, len(ref), feature_angle_deg)[1] & is_boundary
    return UntangleContext(sj_ref, faces, is_boundary, feature, ref_face, _incidence(hexes, len(ref)))


# ----------------------------------------------------------------------------------------------------------
# topology
def boundary_faces(hexes: np.ndarray) -> np.ndarray:
    """Quad faces owned by exactly one hex, outward by the right-hand rule -> (F, 4) node ids."""
    hexes = np.asarray(hexes)
    if hexes.ndim != 2 or hexes.shape[1] != 8:
        raise ValueError(f"hexes must have shape (E, 8), got {hexes.shape}")
    faces = hexes[:, HEX_FACES].reshape(-1, 4).astype(np.int64)
    srt = np.sort(faces, axis=1)
    n = srt.max() + 1 if len(srt) else 1
    hi, lo = srt[:, 0] * n + srt[:, 1], srt[:, 2] * n + srt[:, 3]  # two int64 keys: 4x faster than unique(axis=0)
    order = np.lexsort((lo, hi))
    hi, lo = hi[order], lo[order]
    same_as_next = (hi[1:] == hi[:-1]) & (lo[1:] == lo[:-1])
    shared = np.zeros(len(faces), bool)
    shared[1:] |= same_as_next
    shared[:-1] |= same_as_next
    return faces[order[~shared]]


def boundary_nodes(hexes: np.ndarray) -> np.ndarray:
    """Sorted ids of the nodes on faces owned by exactly one hex (the mesh surface)."""
    return np.unique(boundary_faces(hexes))


def _incidence(hexes: np.ndarray, n_nodes: int) -> scipy.sparse.csr_matrix:
    import scipy.sparse

    E = len(hexes)
    return scipy.sparse.csr_matrix(
        (np.ones(8 * E, dtype=np.int32), (np.repeat(np.arange(E), 8), hexes.ravel())), shape=(E, n_nodes)
    )


def _grow(node_mask: np.ndarray, inc: scipy.sparse.csr_matrix, rings: int) -> np.ndarray:
    for _ in range(rings):
        elems = (inc @ node_mask.astype(np.int32)) > 0
        node_mask = (inc.T @ elems.astype(np.int32)) > 0
    return node_mask


def _quad_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted quad normals from the diagonals -> (F, 3)."""
    return np.cross(points[faces[:, 2]] - points[faces[:, 0]], points[faces[:, 3]] - points[faces[:, 1]])


def _surface_frames(points: np.ndarray, ref_face: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per node: tangent basis (N, 3, 2) of the sample surface.

    Quad normals come from the sample, flipped to agree with the reference quad normals ref_face where a fold
    reversed them.
    """
    n_face = np.cross(points[faces[:, 2]] - points[faces[:, 0]], points[faces[:, 3]] - points[faces[:, 1]])
    n_face *= np.where(np.einsum("ij,ij->i", n_face, ref_face) < 0, -1.0, 1.0)[:, None]
    return _tangent_frames(_node_normals(n_face, faces, len(points), 180.0)[0])


def _tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Two orthonormal tangent vectors per unit normal (n, 3) -> (n, 3, 2)."""
    helper = np.where(np.abs(normals[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True).clip(1e-300)
    return np.stack([t1, np.cross(normals, t1)], axis=-1)


def _surface_near(points: np.ndarray, faces: np.ndarray, node_mask: np.ndarray) -> pv.PolyData:
    """Triangulated surface quads that touch node_mask, as a pyvista PolyData for closest-point queries."""
    from spinecohort.mesh.vtk_mesh import surface

    quads = faces[node_mask[faces].any(1)]
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return surface(points, tris).compute_normals(
        cell_normals=True,
        point_normals=False,
        split_vertices=False,
        consistent_normals=False,
        auto_orient_normals=False,
    )


def _node_normals(n_face, faces, n_nodes, feature_angle_deg):
    nodes = faces.ravel()
    n_node = np.zeros((n_nodes, 3))
    np.add.at(n_node, nodes, np.repeat(n_face, 4, axis=0))
    n_node /= np.linalg.norm(n_node, axis=1, keepdims=True).clip(1e-300)
    unit_face = n_face / np.linalg.norm(n_face, axis=1, keepdims=True).clip(1e-300)
    cos = np.einsum("ij,ij->i", np.repeat(unit_face, 4, axis=0), n_node[nodes])
    min_cos = np.ones(n_nodes)
    np.minimum.at(min_cos, nodes, cos)
    feature = min_cos < np.cos(np.radians(feature_angle_deg))
    return n_node, feature


def _folded_surface_faces(points, ref, faces, bad_nodes) -> bool:
    """True if a surface quad touching a bad element is folded (a corner normal opposes the reference normal).

    Such a fold is made of fixed nodes only, so the fixed-surface attempts cannot succeed.
    """
    faces = faces[np.isin(faces, bad_nodes).any(1)]
    if len(faces) == 0:
        return False
    n_ref = np.cross(ref[faces[:, 2]] - ref[faces[:, 0]], ref[faces[:, 3]] - ref[faces[:, 1]])
    p = points[faces]
    corner_n = np.cross(np.roll(p, -1, axis=1) - p, np.roll(p, 1, axis=1) - p)  # (F, 4, 3)
    return bool((np.einsum("fci,fi->fc", corner_n, n_ref) <= 0).any())


# ----------------------------------------------------------------------------------------------------------
# energy
def _sample_point_operators() -> np.ndarray:
    """G (9, 8, 3): edge-vector matrix A[:, j] = sum_n P_n G[k, n, j] at the 8 corners and the centre."""
    G = np.zeros((9, 8, 3))
    for i in range(8):
        G[i, i, :] = -1.0
        for j in range(3):
            G[i, CORNER_NEIGHBOURS[i, j], j] += 1.0
    # centre: principal axes / 4 = dX/du, dX/dv, dX/dw at the centre
    G[8, [1, 2, 5, 6], 0], G[8, [0, 3, 4, 7], 0] = 0.25, -0.25
    G[8, [3, 2, 7, 6], 1], G[8, [0, 1, 4, 5], 1] = 0.25, -0.25
    G[8, [4, 5, 6, 7], 2], G[8, [0, 1, 2, 3], 2] = 0.25, -0.25
    return G


_G = _sample_point_operators()


def winslow_energy(Xe: np.ndarray, Winv: np.ndarray, eps: float, lam: float = 1.0):
    """Regularised Winslow energy of hexes Xe (E, 8, 3) against targets Winv (E, 9, 3, 3) -> (F, dF/dXe, det T).

    F = sum over elements and the 9 sample points of |T|^2/(3 chi^(2/3)) + lam (det^2 + 1)/(2 chi).
    """
    A = np.einsum("knj,enx->ekxj", _G, Xe)
    T = A @ Winv
    t0, t1, t2 = T[..., 0], T[..., 1], T[..., 2]
    cof = np.stack([np.cross(t1, t2), np.cross(t2, t0), np.cross(t0, t1)], axis=-1)
    d = np.einsum("...i,...i->...", t0, cof[..., 0])
    S = np.einsum("...ij,...ij->...", T, T)
    r = np.sqrt(d * d + eps * eps)
    chi = np.where(d >= 0, 0.5 * (d + r), 0.5 * eps * eps / np.where(d >= 0, 1.0, r - d))  # stable for d << 0
    chi23 = chi ** (2.0 / 3.0)
    F = (S / (3.0 * chi23) + lam * (d * d + 1.0) / (2.0 * chi)).sum()
    dchi = 0.5 * (1.0 + d / r)
    dF_dchi = -(2.0 / 9.0) * S / (chi23 * chi) - lam * (d * d + 1.0) / (2.0 * chi * chi)
    dF_dd = lam * d / chi + dF_dchi * dchi
    dT = (2.0 / (3.0 * chi23))[..., None, None] * T + dF_dd[..., None, None] * cof
    dA = dT @ np.swapaxes(Winv, -1, -2)
    return F, np.einsum("ekxj,knj->enx", dA, _G), d


# ----------------------------------------------------------------------------------------------------------
def _bad_elements(points, hexes, target):
    """Scaled Jacobian, invalid (sJ <= 0 or not certified: exact) and below-target masks of all elements."""
    sj = min_scaled_jacobian_nb(points, hexes)
    invalid = (sj <= 0) | (certify_valid(points, hexes) < 0)
    return sj, invalid, invalid | (sj <= target)


def _recheck(new, hexes, target, elems, before):
    """_bad_elements after an attempt that changed only the elements ``elems`` (others keep ``before``)."""
    sj, invalid, below = (a.copy() for a in before)
    sj[elems], invalid[elems], below[elems] = _bad_elements(new, hexes[elems], target[elems])
    return sj, invalid, below


def _attempt(
    points,
    ref,
    hexes,
    faces,
    bad,
    rings,
    sliding,
    frames,
    feature,
    is_boundary,
    inc,
    target,
    mu,
    lam,
    max_outer,
    maxiter,
):
    """One untangling attempt; returns repaired points (copy) and patch element ids.

    Sliding nodes move in their tangent plane during L-BFGS and are then projected back onto the sample's
    input surface (its boundary quads split into triangles), so they stay on the morphed surface.
    """
    from scipy.optimize import minimize

    seed = np.zeros(len(points), bool)
    seed[hexes[bad].ravel()] = True
    patch = _grow(seed, inc, rings)
    if sliding:
        movable = patch & ~feature
    else:
        movable = patch & ~is_boundary
    slide = movable & is_boundary
    elems = np.flatnonzero((inc @ movable.astype(np.int32)) > 0)
    if len(elems) == 0:
        return None, elems
    ehex = hexes[elems]
    local_nodes, local_conn = np.unique(ehex, return_inverse=True)
    local_conn = local_conn.reshape(ehex.shape)
    x0 = points[local_nodes].copy()
    W = np.einsum("knj,enx->ekxj", _G, ref[ehex])
    Winv = np.linalg.inv(W)
    h = np.linalg.norm(ref[ehex][:, HEX_EDGES[:, 1]] - ref[ehex][:, HEX_EDGES[:, 0]], axis=-1).mean()
    free3 = np.flatnonzero(movable[local_nodes] & ~slide[local_nodes])
    free2 = np.flatnonzero(slide[local_nodes])
    B = frames[local_nodes[free2]]  # (n2, 3, 2)
    n3 = 3 * len(free3)
    base = x0.copy()  # sliding nodes: x = base + B s
    if len(free2):
        surface = _surface_near(points, faces, _grow(patch, inc, 1))

    def positions(z):
        x = base.copy()
        x[free3] = z[:n3].reshape(-1, 3)
        x[free2] += np.einsum("nij,nj->ni", B, z[n3:].reshape(-1, 2))
        return x

    def fun(z, eps):
        x = positions(z)
        F, dXe, _ = winslow_energy(x[local_conn], Winv, eps, lam)
        g = np.zeros_like(x)
        for c in range(3):
            g[:, c] = np.bincount(local_conn.ravel(), weights=dXe[..., c].ravel(), minlength=len(x))
        dx = x - x0
        F += mu * np.sum(dx**2) / h**2  # dx is 0 on fixed nodes
        g += 2.0 * mu * dx / h**2
        grad = np.concatenate([g[free3].ravel(), np.einsum("nij,ni->nj", B, g[free2]).ravel()])
        return F, grad

    z = np.concatenate([x0[free3].ravel(), np.zeros(2 * len(free2))])
    _, _, d = winslow_energy(x0[local_conn], Winv, 1.0, lam)
    best_min_det = d.min()
    stagnant = 0
    for _ in range(max_outer):
        eps = np.sqrt(1e-8 + 0.04 * min(d.min(), 0.0) ** 2)
        res = minimize(fun, z, args=(eps,), jac=True, method="L-BFGS-B", options={"maxiter": maxiter})
        z = res.x
        x = positions(z)
        if len(free2):
            cell, base[free2] = surface.find_closest_cell(x[free2], return_closest_point=True)
            B = _tangent_frames(surface.cell_normals[cell])
            z[n3:] = 0.0
            x = positions(z)
        _, _, d = winslow_energy(x[local_conn], Winv, 1.0, lam)
        sj = min_scaled_jacobian_nb(x, local_conn)
        if np.all(sj > target[elems]):
            break
        if d.min() <= best_min_det + 1e-12:
            stagnant += 1
            if stagnant >= 3:
                break
        else:
            best_min_det, stagnant = d.min(), 0
    out = points.copy()
    out[local_nodes] = positions(z)
    return out, elems


def untangle(
    points: np.ndarray,
    hexes: np.ndarray,
    reference_points: np.ndarray,
    tau: float = 0.05,
    mu: float = 1.0,
    lam: float = 1.0,
    plan: tuple[tuple[int, bool], ...] = ((1, False), (2, False), (2, True), (3, True)),
    feature_angle_deg: float = 30.0,
    max_outer: int = 20,
    maxiter: int = 300,
    context: UntangleContext | None = None,
    passes: int = 2,
    free_features: bool = True,
) -> tuple[np.ndarray, RepairReport]:
    """Repair inverted / badly shaped hexes of one sample by local untangling.

    points: (N, 3) sample in mm; hexes: (E, 8) VTK/C3D8 order; reference_points: (N, 3) valid mesh with the
    same connectivity (the SSM mean). Element e is bad if its scaled Jacobian <= min(tau, sJ_ref(e)/2) or it
    is not certified valid. plan: (node rings, surface sliding) per escalation step. context: from
    ``prepare_untangle(hexes, reference_points)``, reused across the samples of a cohort (saves ~5 s at 500k hexes).
    Returns (repaired points (N, 3), RepairReport). A mesh without bad elements is returned unchanged (so a
    second call is a no-op). Raises RepairError naming the elements left invalid if every step fails.
    passes: when the best step still leaves invalid elements, the plan runs again from that step's result, up
    to this many times in all (a fold at a thin disc next to a concave real endplate can need two).
    free_features: when every step of the plan leaves invalid elements, one more attempt at its widest sliding
    step lets the surface feature nodes slide as well (a rim fold pinned by them: the L5-S1 cartilage layer under
    L5's flared rim at 3 SD).
    """
    points, hexes = check_mesh(points, hexes)
    ref, _ = check_mesh(reference_points, hexes)
    if points.ndim != 2 or ref.shape != points.shape:
        raise ValueError(f"points {points.shape} and reference_points {ref.shape} must both be (n_nodes, 3)")
    if context is None:
        context = prepare_untangle(hexes, ref, feature_angle_deg)
    elif context.incidence.shape != (len(hexes), len(points)):
        raise ValueError(
            f"context was prepared for {context.incidence.shape} (elements, nodes), "
            f"mesh has {(len(hexes), len(points))}"
        )
    ctx = context
    target = np.minimum(tau, 0.5 * ctx.sj_reference)
    sj0, invalid0, bad0 = _bad_elements(points, hexes, target)
    report = RepairReport(
        int(invalid0.sum()),
        int(invalid0.sum()),
        int(bad0.sum()),
        float(sj0.min()),
        float(sj0.min()),
        np.zeros(0, dtype=np.int64),
        0.0,
    )
    if not bad0.any():
        return points.copy(), report

    faces, is_boundary, feature, inc = ctx.faces, ctx.is_boundary, ctx.feature, ctx.incidence
    frames = _surface_frames(points, ctx.reference_face_normals, faces)
    bad = np.flatnonzero(bad0)

    # a bad corner made only of surface nodes cannot change with a fixed surface: go straight to sliding
    corner_nodes = np.concatenate([hexes[bad][:, :, None], hexes[bad][:, CORNER_NEIGHBOURS]], axis=2)
    inverted_corner = corner_jacobians(points, hexes[bad]) <= 0
    surface_only = bool(is_boundary[corner_nodes].all(-1)[inverted_corner].any()) or _folded_surface_faces(
        points, ref, faces, bad_nodes=hexes[bad]
    )
    steps = ([s for s in plan if s[1]] or list(plan)) if surface_only else list(plan)

    best = None
    for rings, sliding in steps:
        new, elems = _attempt(
            points,
            ref,
            hexes,
            faces,
            bad,
            rings,
            sliding,
            frames,
            feature,
            is_boundary,
            inc,
            target,
            mu,
            lam,
            max_outer,
            maxiter,
        )
        if new is None:
            report.attempts.append(f"rings={rings} sliding={sliding}: no movable node")
            continue
        sj, invalid, below = _recheck(new, hexes, target, elems, (sj0, invalid0, bad0))
        report.attempts.append(
            f"rings={rings} sliding={sliding}: {invalid.sum()} invalid, "
            f"{below.sum()} below target, min sJ {sj.min():.3f}"
        )
        if best is None or (invalid.sum(), below.sum()) < (best[1].sum(), best[2].sum()):
            best = (new, invalid, below, sj, rings, sliding)
        if not below.any():
            break
    if free_features and best is not None and best[1].any() and any(s[1] for s in steps):
        # a fold pinned by a surface feature node (a rim where the wall meets an endplate or disc): the widest
        # step once more, the feature nodes sliding on the sample's surface like the others
        rings = max(s[0] for s in steps if s[1])
        new, elems = _attempt(
            points, ref, hexes, faces, bad, rings, True, frames, np.zeros_like(feature), is_boundary, inc,
            target, mu, lam, max_outer, maxiter,
        )  # fmt: skip
        if new is not None:
            sj, invalid, below = _recheck(new, hexes, target, elems, (sj0, invalid0, bad0))
            report.attempts.append(
                f"rings={rings} sliding=True features sliding: {invalid.sum()} invalid, "
                f"{below.sum()} below target, min sJ {sj.min():.3f}"
            )
            if (invalid.sum(), below.sum()) < (best[1].sum(), best[2].sum()):
                best = (new, invalid, below, sj, rings, True)
    if best is None:
        raise RepairError(
            f"untangling failed: no movable node near the {invalid0.sum()} invalid elements "
            f"(all surface/feature nodes); attempts: {report.attempts}"
        )
    new, invalid, below, sj, rings, sliding = best
    min_sj_after = float(sj.min())
    if invalid.any() and passes > 1 and invalid.sum() < invalid0.sum():
        try:
            new, later = untangle(
                new, hexes, ref, tau, mu, lam, plan, feature_angle_deg, max_outer, maxiter, ctx, passes - 1,
                free_features,
            )  # fmt: skip
        except RepairError as err:
            # the second pass's counts are of the first pass's output, which is discarded with it: the message
            # leads with the mesh as given, the one a caller keeps
            raise RepairError(
                f"untangling failed: the {invalid0.sum()} invalid elements of the input were cut to {invalid.sum()} "
                f"by the first pass, then second pass: {err}; first pass: {report.attempts}"
            ) from None
        invalid = np.zeros(0, bool)
        min_sj_after, rings, sliding = later.min_scaled_jacobian_after, later.patch_rings, later.sliding
        report.attempts.extend(f"pass 2: {a}" for a in later.attempts)
    if invalid.any():
        raise RepairError(
            f"untangling failed: {invalid.sum()} invalid elements remain (input had {invalid0.sum()}; "
            f"e.g. elements {np.flatnonzero(invalid)[:10].tolist()}); attempts: {report.attempts}"
        )
    moved = np.flatnonzero(np.any(new != points, axis=1))
    report.invalid_after = 0
    report.min_scaled_jacobian_after = min_sj_after
    report.moved_nodes = moved
    report.displacement_mm = new[moved] - points[moved]
    report.max_displacement_mm = float(np.linalg.norm(report.displacement_mm, axis=1).max(initial=0.0))
    report.patch_rings, report.sliding = rings, sliding
    return new, report
