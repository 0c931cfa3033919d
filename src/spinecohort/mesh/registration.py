"""Point-set registration: rigid CPD and ICP here; BCPD-style non-rigid in :mod:`spinecohort.mesh.bcpd`,
surface distance in :mod:`spinecohort.mesh.distance`, the samplers in :mod:`spinecohort.mesh.pointsets`.

This module is the one import of the registration tools (``from spinecohort.mesh import registration as
reg``): the names of the other three modules are re-exported.  Why the algorithms are written here rather
than taken from pycpd or probreg, and how the defaults were chosen, is in docs/explanation/registration.md.
Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from spinecohort.mesh.bcpd import NonrigidResult, multilayer_register, nonrigid_register
from spinecohort.mesh.distance import point_triangle_distance, surface_distance
from spinecohort.mesh.pointsets import (
    as_points,
    exp_floor,
    farthest_point_sample,
    similarity_from_moments,
    voxel_downsample,
)

__all__ = [
    "NonrigidResult",
    "RigidResult",
    "farthest_point_sample",
    "icp_rigid",
    "multilayer_register",
    "nonrigid_register",
    "point_triangle_distance",
    "rigid_register",
    "surface_distance",
    "voxel_downsample",
]


@dataclass(frozen=True)
class RigidResult:
    """``transformed = s * source @ R.T + t`` (mm); ``rms`` = RMS closest-point distance to the target."""

    R: np.ndarray
    t: np.ndarray
    s: float
    transformed: np.ndarray
    iterations: int
    rms: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Apply the fitted similarity to other points (mm)."""
        return self.s * np.asarray(points, float) @ self.R.T + self.t


def _rigid_result(source, target, rot, scale, trans, iterations) -> RigidResult:
    moved = scale * source @ rot.T + trans
    rms = float(np.sqrt(np.mean(cKDTree(target).query(moved)[0] ** 2)))
    return RigidResult(rot, trans, float(scale), moved, iterations, rms)


def _cpd_similarity(y, x, scale, w, max_iter, tol):
    """CPD's rigid/similarity EM on normalised points: R, s, t with x ~ s R y + t, and the iteration count.

    Starts with the centroids matched, so a distant source need not be pre-placed."""
    m, n = len(y), len(x)
    rot, s, t = np.eye(3), 1.0, x.mean(0) - y.mean(0)
    sigma2 = float(np.mean(cdist(y + t, x, "sqeuclidean"))) / 3
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        moved = s * y @ rot.T + t
        d2 = cdist(moved, x, "sqeuclidean")
        c = (2 * np.pi * sigma2) ** 1.5 * w / (1 - w) * m / n
        p = exp_floor(-d2 / (2 * sigma2))
        p /= p.sum(axis=0, keepdims=True) + c
        np_ = p.sum()
        if not np_ > 1e-12:
            raise ValueError("rigid CPD lost all correspondences (no target point near the source)")
        mu_x = (p.sum(axis=0) @ x) / np_
        mu_y = (p.sum(axis=1) @ y) / np_
        a = (x - mu_x).T @ p.T @ (y - mu_y)  # 3x3 cross-covariance (target x source)
        yc = y - mu_y
        yy = float(np.sum(p.sum(axis=1) * np.sum(yc**2, axis=1)))
        rot, s_fit = similarity_from_moments(a, yy)
        s = s_fit if scale else 1.0
        t = mu_x - s * rot @ mu_y
        xc = x - mu_x
        xx = float(np.sum(p.sum(axis=0) * np.sum(xc**2, axis=1)))
        new_sigma2 = max((xx - 2 * s * np.trace(a.T @ rot) + s**2 * yy) / (3 * np_), 1e-12)
        converged = abs(sigma2 - new_sigma2) < tol * max(sigma2, 1e-12)
        sigma2 = new_sigma2
        if converged:
            break
    return rot, s, t, it


def _check_transform(rot, s, t, who: str) -> None:
    """A diverged fit (NaN, or a scale collapsed towards 0) is an error, not a silent result."""
    if not (np.all(np.isfinite(rot)) and np.isfinite(s) and np.all(np.isfinite(t))):
        raise ValueError(f"{who} diverged: the transform has NaN or infinite entries (scale {s})")
    if not 0.2 < s < 5.0:
        raise ValueError(f"{who} diverged: scale {s:.3g} (the shapes differ by more than 5x in size; check the units)")


def rigid_register(
    source: np.ndarray,
    target: np.ndarray,
    scale: bool = True,
    w: float = 0.1,
    max_iter: int = 100,
    tol: float = 1e-6,
    max_points: int = 1000,
    refine_icp: bool = True,
    seed: int = 0,
) -> RigidResult:
    """Rigid (``scale=False``) or similarity CPD of ``source`` onto ``target`` (Myronenko & Song 2010).

    This is what BCPD does with lambda = 1e9 (motion frozen) - the seed's rough alignment step.  It runs in
    the target's normalised coordinates (centred, unit RMS radius), so ``w``, the outlier ratio, means the
    same in mm, cm or m; ``max_points`` random points of each set estimate the transform (CPD costs
    O(M N) per iteration), which is then applied to all of ``source``.  CPD's last iterations creep
    (sigma shrinks slowly), so with ``refine_icp`` the estimate is finished by ``icp_rigid`` on all points.
    Converges to the global optimum for rotations up to a few tens of degrees on clearly anisotropic shapes;
    pre-rotate larger ones (the seed turns the template 90 degrees).  A fit that diverges (NaN, or a scale
    outside 0.2-5) raises ValueError.
    """
    src = as_points(source, "source", 3)
    tgt = as_points(target, "target", 3)
    if not 0.0 <= w < 1.0:
        raise ValueError(f"outlier ratio w must be in [0, 1), got {w}")
    rng = np.random.default_rng(seed)
    # Normalised coordinates (target centred, unit RMS radius): CPD's uniform outlier term is a density
    # per point, not per volume, so in mm it outweighs the Gaussians and the scale collapses to ~0.2.
    centre = tgt.mean(axis=0)
    unit = float(np.sqrt(np.mean(np.sum((tgt - centre) ** 2, axis=1))))
    if not unit > 0:
        raise ValueError("target points are all identical")
    y = src[rng.choice(len(src), max_points, replace=False)] if len(src) > max_points else src
    x = tgt[rng.choice(len(tgt), max_points, replace=False)] if len(tgt) > max_points else tgt
    y, x = (y - centre) / unit, (x - centre) / unit
    rot, s, t, it = _cpd_similarity(y, x, scale, w, max_iter, tol)
    t = unit * t + centre - s * rot @ centre  # back to mm
    if refine_icp:
        fine = icp_rigid(s * src @ rot.T + t, tgt, scale=scale)
        rot, s, t = fine.R @ rot, fine.s * s, fine.s * fine.R @ t + fine.t
        it += fine.iterations
    _check_transform(rot, s, t, "rigid_register")
    return _rigid_result(src, tgt, rot, s, t, it)


def icp_rigid(
    source: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray | None = None,
    scale: bool = False,
    max_iter: int = 100,
    tol: float = 1e-10,
    reject_factor: float = 3.0,
) -> RigidResult:
    """Iterative closest point of ``source`` onto target points (mm), via a scipy cKDTree.

    Point-to-point (Kabsch/Umeyama step) by default; point-to-plane (linearised small-angle step, Chen &
    Medioni) when ``target_normals`` (unit, one per target point) are given - converges in far fewer
    iterations on surfaces.  Pairs farther than ``reject_factor`` times the median pair distance are
    ignored (outliers).  Needs a rough initial alignment (e.g. ``rigid_register``).
    """
    src = as_points(source, "source", 3)
    tgt = as_points(target, "target", 3)
    if target_normals is not None:
        normals = as_points(target_normals, "target_normals")
        if len(normals) != len(tgt):
            raise ValueError("target_normals must have one normal per target point")
        if scale:
            raise ValueError("point-to-plane ICP does not estimate scale; use scale=False")
    tree = cKDTree(tgt)
    rot, s, t = np.eye(3), 1.0, np.zeros(3)
    prev = np.inf
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        moved = s * src @ rot.T + t
        dist, idx = tree.query(moved)
        keep = dist <= reject_factor * max(np.median(dist), 1e-12)
        p, q = moved[keep], tgt[idx[keep]]
        if target_normals is None:
            mp, mq = p.mean(0), q.mean(0)
            pc = p - mp
            d_rot, d_s = similarity_from_moments((q - mq).T @ pc, float(np.sum(pc**2)))
            d_s = d_s if scale else 1.0
            d_t = mq - d_s * d_rot @ mp
        else:
            nq = normals[idx[keep]]
            # Linearised rotation: minimise sum ((p + w x p + dt - q) . n)^2 over (w, dt).
            a = np.hstack([np.cross(p, nq), nq])
            b = np.einsum("ij,ij->i", q - p, nq)
            xw, *_ = np.linalg.lstsq(a, b, rcond=None)
            wx, wy, wz = xw[:3]
            skew = np.array([[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]])
            u, _, vt = np.linalg.svd(np.eye(3) + skew)  # project onto the nearest rotation
            d_rot, d_s, d_t = u @ vt, 1.0, xw[3:]
        rot, s, t = d_rot @ rot, d_s * s, d_s * d_rot @ t + d_t
        err = float(np.mean(dist[keep] ** 2))
        if abs(prev - err) <= tol * max(err, 1e-12) or err < 1e-20:
            break
        prev = err
    _check_transform(rot, s, t, "icp_rigid")
    return _rigid_result(src, tgt, rot, s, t, it)
