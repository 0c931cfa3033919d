"""Point-set helpers shared by the rigid and the non-rigid registration (coordinates in mm unless named).

Input checks, an underflow-safe exponential, the Umeyama similarity step, and the two samplers BCPD++
relies on: a voxel grid (even sampling of a surface) and farthest-point sampling (Nystrom landmarks).
"""

from __future__ import annotations

import numpy as np

#: entries of one dense M x block correspondence block (~32 MB of float64)
BLOCK_ENTRIES = 4_000_000


def exp_floor(arg: np.ndarray) -> np.ndarray:
    """exp of non-positive arguments floored at -700: results in exp's subnormal range (args -708 to -745)
    run ~45x slower on x86 and carry no weight next to the other terms."""
    return np.exp(np.maximum(arg, -700.0))


def as_points(points: np.ndarray, name: str, min_points: int = 1) -> np.ndarray:
    arr = np.asarray(points, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array of points in mm, got shape {arr.shape}")
    if arr.shape[0] < min_points:
        raise ValueError(f"{name} needs at least {min_points} points, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite coordinates")
    return arr


def similarity_from_moments(sxu: np.ndarray, suu_trace: float) -> tuple[np.ndarray, float]:
    """Rotation and scale maximising tr(R^T Sxu) (Umeyama), proper rotation enforced."""
    u, d, vt = np.linalg.svd(sxu)
    c = np.ones(3)
    c[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = (u * c) @ vt
    scale = float(np.sum(d * c) / suu_trace)
    return rot, scale


def voxel_downsample(points: np.ndarray, radius: float) -> np.ndarray:
    """Indices of one point per cubic voxel of edge ``radius`` mm (the point nearest the voxel mean).

    BCPD++ registers downsampled sets and interpolates the motion back; a voxel grid keeps the sampling
    even over the surface, which the Gaussian mixture assumes.  ``radius <= 0`` keeps every point.
    """
    pts = as_points(points, "points")
    if radius <= 0:
        return np.arange(len(pts))
    keys = np.floor((pts - pts.min(axis=0)) / radius).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    means = np.zeros((len(counts), 3))
    np.add.at(means, inverse, pts)
    means /= counts[:, None]
    d2 = np.sum((pts - means[inverse]) ** 2, axis=1)
    order = np.lexsort((d2, inverse))  # within each voxel, nearest-to-mean first
    first = np.ones(len(order), dtype=bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    return np.sort(order[first])


def farthest_point_sample(points: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Indices of ``k`` points spread by farthest-point sampling (Nystrom landmarks covering the shape).

    BCPD samples landmarks at random; farthest-point sampling covers a surface evenly with fewer of them,
    which matters when the kernel width is small.  The loop runs over the k landmarks, each step vectorised
    over all points.
    """
    n = len(points)
    k = min(int(k), n)
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = np.random.default_rng(seed).integers(n)
    d2 = np.sum((points - points[chosen[0]]) ** 2, axis=1)
    for i in range(1, k):
        chosen[i] = int(np.argmax(d2))
        d2 = np.minimum(d2, np.sum((points - points[chosen[i]]) ** 2, axis=1))
    return chosen
