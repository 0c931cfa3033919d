"""Principal component analysis of aligned shapes (the statistical shape model).

PCA by thin SVD of the mean-centred (P, 3N) data matrix: with X_c = U S V^T the modes are the rows of V^T
(unit vectors in R^{3N}) and the covariance eigenvalues d_i = S_i^2 / (P - 1) (mm^2), the seed's
Equation 1-3 without forming the 3N x 3N covariance.  Shapes are sampled with the seed's Equation 4:
``shape = mean + sum_i sqrt(d_i) * phi_i * w_i`` with w_i in standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class SSM:
    mean: np.ndarray  # (N, 3) mm
    modes: np.ndarray  # (M, N, 3) orthonormal as flattened vectors
    eigenvalues: np.ndarray  # (M,) mm^2, descending
    n_train: int

    @property
    def n_modes(self) -> int:
        return int(self.eigenvalues.shape[0])

    @property
    def explained_variance_ratio(self) -> np.ndarray:
        return self.eigenvalues / self.eigenvalues.sum()

    @property
    def cumulative_variance(self) -> np.ndarray:
        """Compactness C(m) = sum_{j<=m} d_j / sum_j d_j (seed Equation 5)."""
        return np.cumsum(self.explained_variance_ratio)

    def modes_for_variance(self, threshold: float = 0.95) -> int:
        """Smallest number of modes whose cumulative variance reaches ``threshold``."""
        return int(np.searchsorted(self.cumulative_variance, threshold - 1e-12) + 1)

    def deformation_fields(self, n_modes: int | None = None) -> np.ndarray:
        """(m, N, 3) sqrt(d_i) * phi_i: displacement in mm per +1 SD of each mode."""
        m = self.n_modes if n_modes is None else n_modes
        return self.modes[:m] * np.sqrt(self.eigenvalues[:m])[:, None, None]

    def sample(self, weights: np.ndarray) -> np.ndarray:
        """Shapes (B, N, 3) mm for weights (B, m) in SD units (or (m,) for one shape)."""
        w = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        df = self.deformation_fields(w.shape[1])
        out = self.mean + np.tensordot(w, df, axes=(1, 0))
        return out if np.ndim(weights) == 2 else out[0]

    def project(self, shapes: np.ndarray, n_modes: int | None = None) -> np.ndarray:
        """Weights (B, m) in SD units of the least-squares fit of aligned shapes (B, N, 3) in mode space."""
        m = self.n_modes if n_modes is None else n_modes
        x = np.atleast_3d(shapes).reshape(-1, self.mean.size) - self.mean.ravel()
        coeff = x @ self.modes[:m].reshape(m, -1).T
        return coeff / np.sqrt(self.eigenvalues[:m])

    def save(self, path: str | Path, **extra) -> None:
        np.savez(path, mean=self.mean, modes=self.modes, eigenvalues=self.eigenvalues, n_train=self.n_train, **extra)

    @classmethod
    def load(cls, path: str | Path, n_modes: int | None = None) -> SSM:
        """The SSM saved by :meth:`save`; with ``n_modes``, only its first n_modes modes and their eigenvalues,
        so the ratios of explained variance are then those of the kept modes."""
        with np.load(path) as z:
            mean, modes, eigenvalues, n_train = z["mean"], z["modes"], z["eigenvalues"], int(z["n_train"])
        if n_modes is None:
            return cls(mean, modes, eigenvalues, n_train)
        if not 1 <= n_modes <= len(eigenvalues):
            raise ValueError(f"{path}: asked for {n_modes} modes, the SSM has {len(eigenvalues)}")
        return cls(mean, np.array(modes[:n_modes]), eigenvalues[:n_modes], n_train)


def build_ssm(aligned: np.ndarray, rel_tol: float = 1e-10) -> SSM:
    """PCA of aligned shapes (P, N, 3) mm; keeps the modes with non-negligible variance (at most P - 1)."""
    p, n, _ = aligned.shape
    if p < 3:
        raise ValueError(f"an SSM needs at least 3 shapes, got {p}")
    mean = aligned.mean(0)
    x = (aligned - mean).reshape(p, -1)
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    ev = s**2 / (p - 1)
    keep = ev > rel_tol * ev[0]
    vt = vt[keep]
    # Deterministic signs: the largest-magnitude component of each mode is positive.
    idx = np.argmax(np.abs(vt), axis=1)
    vt *= np.sign(vt[np.arange(len(vt)), idx])[:, None]
    return SSM(mean, vt.reshape(-1, n, 3), ev[keep], p)
