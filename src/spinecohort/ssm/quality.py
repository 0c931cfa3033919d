"""Standard SSM quality measures: compactness, generalization and specificity (Davies; Styner et al. 2003).

Distances are per-vertex RMS: ``sqrt(mean_v |x_v - y_v|^2)`` in mm between two shapes in correspondence.

Both measures are computed exactly in the space spanned by the training shapes, from their Gram matrix
(P x P) and mode coordinates, never by reconstructing 3N-vectors: leave-one-out generalization of a
42-shape model with 10^5 vertices then costs milliseconds instead of forming 42 x 41 full reconstructions.
Generalization uses the GPA-aligned shapes (the left-out shape is not re-aligned), as is common practice.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from spinecohort.ssm.model import SSM


def generalization_errors(aligned: np.ndarray, max_modes: int | None = None) -> np.ndarray:
    """(P, m_max) RMS error (mm) of reconstructing shape i with m modes of a PCA of the other shapes."""
    p, n, _ = aligned.shape
    x = (aligned - aligned.mean(0)).reshape(p, -1)
    g = x @ x.T
    m_max = p - 2 if max_modes is None else min(max_modes, p - 2)
    errs = np.empty((p, m_max))
    for i in range(p):  # P small Gram problems, each a (P-1) x (P-1) eigendecomposition
        tr = np.delete(np.arange(p), i)
        gtt = g[np.ix_(tr, tr)]
        gti = g[tr, i]
        row_mean = gtt.mean(1)
        k = gtt - row_mean[:, None] - row_mean[None, :] + gtt.mean()
        inner = gti - row_mean - gti.mean() + gtt.mean()  # (x_T - mu) . (x_i - mu)
        r2 = g[i, i] - 2 * gti.mean() + gtt.mean()  # |x_i - mu|^2
        lam, u = np.linalg.eigh(k)
        order = np.argsort(lam)[::-1][:m_max]
        lam, u = lam[order], u[:, order]
        c2 = np.where(lam > 1e-12 * lam[0], (u.T @ inner) ** 2 / np.maximum(lam, 1e-300), 0.0)
        errs[i] = np.sqrt(np.maximum(r2 - np.cumsum(c2), 0.0) / n)
    return errs


def generalization(aligned: np.ndarray, max_modes: int | None = None) -> pd.DataFrame:
    """Leave-one-out reconstruction error versus number of modes.

    For each shape i, a PCA of the other P - 1 shapes reconstructs shape i with its first m modes.
    Returns rows m = 1..max_modes with ``generalization_mm`` (mean over i) and ``generalization_sd_mm``.
    """
    errs = generalization_errors(aligned, max_modes)
    m_max = errs.shape[1]
    return pd.DataFrame(
        {
            "modes": np.arange(1, m_max + 1),
            "generalization_mm": errs.mean(0),
            "generalization_sd_mm": errs.std(0, ddof=1),
        }
    )


def specificity(
    ssm: SSM, aligned: np.ndarray, n_samples: int = 1000, max_modes: int | None = None, seed: int = 0
) -> pd.DataFrame:
    """Distance of random model instances (w ~ N(0, I)) to their nearest training shape, per m modes.

    Training shapes lie in the span of the modes, so |s - x_j|^2 = |c - a_j[:m]|^2 + |a_j[m:]|^2 with
    c = sqrt(d) w the sample's and a_j the training shape's mode coordinates (mm).
    """
    p, n, _ = aligned.shape
    a = (aligned - ssm.mean).reshape(p, -1) @ ssm.modes.reshape(ssm.n_modes, -1).T  # (P, M)
    resid_tot = ((aligned - ssm.mean).reshape(p, -1) ** 2).sum(1)
    m_max = ssm.n_modes if max_modes is None else min(max_modes, ssm.n_modes)
    rng = np.random.default_rng(seed)
    rows = []
    for m in range(1, m_max + 1):
        c = rng.standard_normal((n_samples, m)) * np.sqrt(ssm.eigenvalues[:m])
        tail = resid_tot - (a[:, :m] ** 2).sum(1)  # |a_j[m:]|^2 (+ anything outside the span)
        d2 = ((c[:, None, :] - a[None, :, :m]) ** 2).sum(-1) + np.maximum(tail, 0.0)[None]
        dist = np.sqrt(d2.min(1) / n)
        rows.append((m, dist.mean(), dist.std(ddof=1)))
    return pd.DataFrame(rows, columns=["modes", "specificity_mm", "specificity_sd_mm"])


def compactness_table(ssm: SSM) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "modes": np.arange(1, ssm.n_modes + 1),
            "eigenvalue_mm2": ssm.eigenvalues,
            "sd_mm": np.sqrt(ssm.eigenvalues),
            "explained_variance": ssm.explained_variance_ratio,
            "cumulative_variance": ssm.cumulative_variance,
        }
    )
