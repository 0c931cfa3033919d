"""Generalized Procrustes alignment (GPA) of shapes in vertex correspondence.

Follows the seed's Methods: take a reference shape, align every shape to it, average, take the average as
the new reference and iterate until the mean stops moving.  Alignment is rigid (rotation + translation) by
default; ``scaling=True`` adds an isotropic scale per shape (similarity GPA), with the mean kept at the
centroid size of the initial reference so that the iteration cannot shrink it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


def kabsch(source: np.ndarray, target: np.ndarray, scaling: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best rigid (or similarity) maps ``target ~ s * source @ R.T + t`` for a batch of shapes.

    source: (..., N, 3), target: (N, 3) or (..., N, 3), in mm.  Returns R (..., 3, 3) proper rotations,
    s (...,) scales (1 when ``scaling`` is False) and t (..., 3) translations in mm.
    """
    src_c = source.mean(axis=-2, keepdims=True)
    tgt_c = target.mean(axis=-2, keepdims=True)
    x = source - src_c
    y = target - tgt_c
    h = np.einsum("...ni,...nj->...ij", x, y)  # cross-covariance
    u, sig, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("...ij,...jk->...ik", u, vt)))
    corr = np.ones(sig.shape)
    corr[..., -1] = d  # no reflections
    r = np.einsum("...ji,...j,...kj->...ik", vt, corr, u)  # R = V diag(1,1,d) U^T
    if scaling:
        s = (sig * corr).sum(-1) / np.einsum("...ni,...ni->...", x, x)
    else:
        s = np.ones(sig.shape[:-1])
    t = tgt_c[..., 0, :] - s[..., None] * np.einsum("...ij,...j->...i", r, src_c[..., 0, :])
    return r, s, t


def apply_transform(points: np.ndarray, r: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``s * points @ R.T + t`` for batches as returned by :func:`kabsch`."""
    return s[..., None, None] * np.einsum("...ij,...nj->...ni", r, points) + t[..., None, :]


@dataclass
class GPAResult:
    aligned: np.ndarray  # (P, N, 3) mm
    mean: np.ndarray  # (N, 3) mm
    rotations: np.ndarray  # (P, 3, 3): aligned = s * original @ R.T + t
    scales: np.ndarray  # (P,)
    translations: np.ndarray  # (P, 3)
    n_iterations: int
    mean_change_mm: list[float]  # RMS change of the mean per iteration


def procrustes_align(
    shapes: np.ndarray, scaling: bool = False, tol_mm: float = 1e-6, max_iter: int = 100, reference_index: int = 0
) -> GPAResult:
    """Generalized Procrustes alignment of (P, N, 3) shapes in mm.

    The result is expressed in the frame of the cohort's average posture: the converged mean is finally
    rigidly aligned to the plain average of the input shapes, so for standing (EOS) reconstructions the
    SSM's z axis stays the scanner vertical on average, and its centroid is put at the origin.
    Convergence: RMS per-vertex change of the mean below ``tol_mm``.
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    if shapes.ndim != 3 or shapes.shape[-1] != 3 or shapes.shape[0] < 2:
        raise ValueError(f"procrustes_align needs (P >= 2, N, 3) shapes, got {shapes.shape}")
    ref = shapes[reference_index] - shapes[reference_index].mean(0)
    size0 = np.sqrt((ref**2).sum())
    history: list[float] = []
    for _it in range(1, max_iter + 1):
        r, s, t = kabsch(shapes, ref, scaling)
        aligned = apply_transform(shapes, r, s, t)
        mean = aligned.mean(0)
        # Re-anchor the new mean on the previous reference so the frame does not drift.
        rm, sm, tm = kabsch(mean, ref, False)
        mean = apply_transform(mean, rm, sm, tm)
        if scaling:
            mean = mean * (size0 / np.sqrt((mean**2).sum()))
        change = float(np.sqrt(((mean - ref) ** 2).sum(-1).mean()))
        history.append(change)
        ref = mean
        if change < tol_mm:
            break
    else:
        log.warning("GPA did not converge in %d iterations (last change %.3g mm)", max_iter, history[-1])
    # Final frame: the cohort's average posture, centred.
    raw_avg = shapes.mean(0)
    rf, _, _ = kabsch(ref, raw_avg, False)
    ref = (ref - ref.mean(0)) @ rf.T
    r, s, t = kabsch(shapes, ref, scaling)
    aligned = apply_transform(shapes, r, s, t)
    log.info("GPA converged in %d iterations (mean change %.2e mm)", len(history), history[-1])
    return GPAResult(aligned, aligned.mean(0), r, s, t, len(history), history)
