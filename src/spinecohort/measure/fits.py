"""Batched least-squares fits of the measurement: total-least-squares endplate planes and algebraic femoral-head
spheres of every model of a batch at once.

Planes: the raw moments of all patches of all models summed in one numba pass over the batch (each patch about
its own first vertex: out-of-plane RMS exact to ~1e-9 mm), then the smallest eigenpair of every 3x3 covariance
(one numba pass of Jacobi rotations); normals oriented along the vertical.  Spheres: batched normal equations on
mean-centred points, moments in one pass.  Written here (small numba loops) because scipy/pyvista fit one point
set at a time; a Python loop over 16,807 models x 35 patches would dominate the run time, and the numpy form (a
gathered copy of every landmark vertex, a matmul per patch) costs 2.5x the time
(docs/explanation/performance.md).  Millimetres.
"""

from __future__ import annotations

import numba
import numpy as np


def fit_planes(patch: np.ndarray, vertical: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares planes of a batch of patches.

    patch: (B, K, 3) mm.  Returns centre (B, 3) = vertex mean, unit normal (B, 3) oriented so that
    normal.vertical > 0, and rms (B,) = out-of-plane RMS residual in mm (sqrt of the smallest eigenvalue of
    the covariance, equal to S[-1]/sqrt(K) of the SVD formulation).

    :func:`plane_fits` with one patch: raw moments about the first vertex (no centred copy), so round-off
    stays far below 1e-5 mm wherever the model lies.
    """
    patch = np.asarray(patch, dtype=float)
    centre, normal, rms = plane_fits(patch, {"patch": np.arange(patch.shape[1])}, 0, np.asarray(vertical, float))
    return centre[:, 0] + patch[:, 0], normal[:, 0], rms[:, 0]


@numba.njit(cache=True)
def _patch_moments_nb(points, rows, starts, origin_row):
    """Mean (B, P, 3) and covariance (B, P, 3, 3) of the patches ``rows[starts[j]:starts[j + 1]]`` of points
    (B, N, 3), relative to each model's vertex ``origin_row``: raw moments read straight from the batch (no
    gathered copy), one pass per model."""
    n_models, n_patches = points.shape[0], starts.shape[0] - 1
    mean = np.empty((n_models, n_patches, 3))
    cov = np.empty((n_models, n_patches, 3, 3))
    for b in range(n_models):
        o0, o1, o2 = (
            np.float64(points[b, origin_row, 0]),
            np.float64(points[b, origin_row, 1]),
            np.float64(points[b, origin_row, 2]),
        )
        for j in range(n_patches):
            # moments about the patch's first vertex: coordinates of the patch's size keep the cancellation in
            # E[q q^T] - E[q] E[q]^T small (out-of-plane RMS of 1e-5 mm patches to ~2e-9 mm), then shifted to the
            # model's origin
            r0 = rows[starts[j]]
            p0, p1, p2 = np.float64(points[b, r0, 0]), np.float64(points[b, r0, 1]), np.float64(points[b, r0, 2])
            sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
            for k in range(starts[j], starts[j + 1]):
                r = rows[k]
                x = np.float64(points[b, r, 0]) - p0
                y = np.float64(points[b, r, 1]) - p1
                z = np.float64(points[b, r, 2]) - p2
                sx += x
                sy += y
                sz += z
                sxx += x * x
                sxy += x * y
                sxz += x * z
                syy += y * y
                syz += y * z
                szz += z * z
            n = starts[j + 1] - starts[j]
            mx, my, mz = sx / n, sy / n, sz / n
            mean[b, j, 0], mean[b, j, 1], mean[b, j, 2] = mx + (p0 - o0), my + (p1 - o1), mz + (p2 - o2)
            cov[b, j, 0, 0] = sxx / n - mx * mx
            cov[b, j, 1, 1] = syy / n - my * my
            cov[b, j, 2, 2] = szz / n - mz * mz
            cov[b, j, 0, 1] = cov[b, j, 1, 0] = sxy / n - mx * my
            cov[b, j, 0, 2] = cov[b, j, 2, 0] = sxz / n - mx * mz
            cov[b, j, 1, 2] = cov[b, j, 2, 1] = syz / n - my * mz
    return mean, cov


def plane_fits(points: np.ndarray, patches: dict[str, np.ndarray], origin_row: int, vertical: np.ndarray):
    """TLS planes of every patch of every model in one pass and one pass of Jacobi rotations: points (B, N, 3) mm,
    patches name -> vertex rows.  Returns centres (B, P, 3) relative to each model's vertex ``origin_row``, unit
    normals (B, P, 3) with normal.vertical > 0, out-of-plane RMS (B, P) mm, patches in the dict's order.  Raw
    moments, each patch about its own first vertex (its coordinates stay of the patch's size)."""
    rows = [np.asarray(v, dtype=np.int64).ravel() for v in patches.values()]
    starts = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
    mean, cov = _patch_moments_nb(points, np.concatenate(rows), starts, origin_row)
    if not np.isfinite(cov).all():
        name = list(patches)[int(np.argmax(~np.isfinite(cov).all(axis=(0, 2, 3))))]
        raise ValueError(f"non-finite coordinates in landmark set {name}")
    w0, normal = np.empty(cov.shape[:-2]), np.empty(cov.shape[:-1])
    _least_eigenpairs_nb(cov.reshape(-1, 3, 3), w0.reshape(-1), normal.reshape(-1, 3))
    normal *= np.where(normal @ vertical < 0, -1.0, 1.0)[..., None]
    return mean, normal, np.sqrt(np.clip(w0, 0.0, None))


@numba.njit(cache=True, error_model="numpy")
def _least_eigenpairs_nb(cov, w0, v0):
    """The smallest eigenvalue w0 (M,) and a unit eigenvector v0 (M, 3) of each symmetric 3x3 matrix of cov
    (M, 3, 3), by cyclic Jacobi rotations (Rutishauser's form, as in Numerical Recipes' ``jacobi``).

    Written here rather than ``np.linalg.eigh`` because LAPACK's per-matrix overhead made that ~0.9-1.3 us per
    3x3 matrix (2 x 35 patches x 16,807 models per store stage); this takes 0.27-0.38 us (the stage's measure
    phase: 4.2 s CPU against 4.9 s with ``eigh``; docs/explanation/performance.md).  Jacobi is accurate to
    round-off in every eigenpair, including the nearly-zero out-of-plane variance of a flat patch beside two nearly
    equal in-plane ones (tested against LAPACK)."""
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    for m in range(cov.shape[0]):
        for i in range(3):
            for j in range(3):
                a[i, j] = cov[m, i, j]
                v[i, j] = 1.0 if i == j else 0.0
        for sweep in range(50):
            off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
            # converged: an off-diagonal of 1e-18 x the trace tilts an eigenvector by ~1e-18 x trace / gap
            # and moves an eigenvalue by its square over the gap, far below the round-off of the moments
            if off <= 1e-18 * (abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2])):
                break
            for p, q, r in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
                apq = a[p, q]
                small = 100.0 * abs(apq)
                if sweep > 3 and abs(a[p, p]) + small == abs(a[p, p]) and abs(a[q, q]) + small == abs(a[q, q]):
                    a[p, q] = a[q, p] = 0.0  # below the diagonal's round-off: converged
                    continue
                if apq == 0.0:
                    continue
                h = a[q, q] - a[p, p]
                if abs(h) + small == abs(h):
                    t = apq / h  # tan of the angle ~ its half-angle formula's limit
                else:
                    theta = 0.5 * h / apq
                    t = 1.0 / (abs(theta) + np.sqrt(1.0 + theta * theta))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = t * c
                tau = s / (1.0 + c)
                a[p, p] -= t * apq
                a[q, q] += t * apq
                a[p, q] = a[q, p] = 0.0
                arp, arq = a[r, p], a[r, q]
                a[r, p] = a[p, r] = arp - s * (arq + tau * arp)
                a[r, q] = a[q, r] = arq + s * (arp - tau * arq)
                for i in range(3):
                    vip, viq = v[i, p], v[i, q]
                    v[i, p] = vip - s * (viq + tau * vip)
                    v[i, q] = viq + s * (vip - tau * viq)
        k = 0
        if a[1, 1] < a[k, k]:
            k = 1
        if a[2, 2] < a[k, k]:
            k = 2
        w0[m] = a[k, k]
        for i in range(3):
            v0[m, i] = v[i, k]


@numba.njit(cache=True)
def _sphere_moments_nb(pts):
    """Per model of pts (B, K, 3): mean (B, 3), and of the centred points q: sum q q^T (B, 3, 3), sum q |q|^2
    (B, 3) and mean |q|^2 (B,).  Two passes over the points, no temporary arrays."""
    n_models, k = pts.shape[0], pts.shape[1]
    mu, qq, qs, s_mean = (
        np.empty((n_models, 3)),
        np.empty((n_models, 3, 3)),
        np.empty((n_models, 3)),
        np.empty(n_models),
    )
    for b in range(n_models):
        sx = sy = sz = 0.0
        for i in range(k):
            sx += pts[b, i, 0]
            sy += pts[b, i, 1]
            sz += pts[b, i, 2]
        mx, my, mz = sx / k, sy / k, sz / k
        xx = xy = xz = yy = yz = zz = rx = ry = rz = ss = 0.0
        for i in range(k):
            x, y, z = pts[b, i, 0] - mx, pts[b, i, 1] - my, pts[b, i, 2] - mz
            s = x * x + y * y + z * z
            xx += x * x
            xy += x * y
            xz += x * z
            yy += y * y
            yz += y * z
            zz += z * z
            rx += x * s
            ry += y * s
            rz += z * s
            ss += s
        mu[b, 0], mu[b, 1], mu[b, 2] = mx, my, mz
        qq[b, 0, 0], qq[b, 1, 1], qq[b, 2, 2] = xx, yy, zz
        qq[b, 0, 1] = qq[b, 1, 0] = xy
        qq[b, 0, 2] = qq[b, 2, 0] = xz
        qq[b, 1, 2] = qq[b, 2, 1] = yz
        qs[b, 0], qs[b, 1], qs[b, 2] = rx, ry, rz
        s_mean[b] = ss / k
    return mu, qq, qs, s_mean


def fit_spheres(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic least-squares spheres of a batch of point sets (works on partial caps).

    pts: (B, K, 3) mm.  Solves [2x 2y 2z 1][c; d] = x^2+y^2+z^2 on mean-centred points (for conditioning).
    Returns centre (B, 3) and radius (B,) in mm.
    """
    mu, qq, qs, s_mean = _sphere_moments_nb(np.asarray(pts, dtype=float))
    # centred points make the column of ones orthogonal to the 2q columns, so the 4x4 normal equations split
    # into a 3x3 system for the centre offset and d = mean(|q|^2)
    c = 0.5 * np.linalg.solve(qq, qs[:, :, None])[:, :, 0]
    return mu + c, np.sqrt(s_mean + np.einsum("bi,bi->b", c, c))
