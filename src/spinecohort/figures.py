"""Figures a person would rather look at than read: compactness and quality curves (matplotlib) and
shape-mode variation renderings (pyvista, off-screen)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from .pca import SSM  # noqa: E402


def compactness_plot(table: pd.DataFrame, threshold: float, path: str | Path, max_modes: int = 20) -> None:
    """Explained variance per mode (bars) and cumulative variance (line) with the threshold marked."""
    t = table.head(max_modes)
    n95 = int(np.searchsorted(table["cumulative_variance"].to_numpy(), threshold - 1e-12) + 1)
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=150)
    ax.bar(t["modes"], 100 * t["explained_variance"], color="#8fb3d9", label="per mode")
    ax.plot(t["modes"], 100 * t["cumulative_variance"], "o-", color="#1f4e79", label="cumulative")
    ax.axhline(100 * threshold, color="#c0392b", ls="--", lw=1)
    ax.axvline(n95, color="#c0392b", ls=":", lw=1)
    ax.text(n95 + 0.2, 100 * threshold - 8, f"{100 * threshold:.0f} % at {n95} modes", color="#c0392b")
    ax.set_xlabel("number of modes")
    ax.set_ylabel("explained variance [%]")
    ax.set_ylim(0, 102)
    ax.set_title("SSM compactness")
    ax.legend(loc="center right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def quality_plot(gen: pd.DataFrame, spec: pd.DataFrame, path: str | Path) -> None:
    """Generalization and specificity (mean +/- SD, mm) versus the number of modes."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=150)
    for ax, df, key, title in ((axes[0], gen, "generalization", "Generalization (leave-one-out)"),
                               (axes[1], spec, "specificity", "Specificity (random samples)")):
        m, mu, sd = df["modes"], df[f"{key}_mm"], df[f"{key}_sd_mm"]
        ax.plot(m, mu, "o-", color="#1f4e79")
        ax.fill_between(m, mu - sd, mu + sd, color="#8fb3d9", alpha=0.5)
        ax.set_xlabel("number of modes")
        ax.set_ylabel("per-vertex RMS distance [mm]")
        ax.set_title(title)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _polydata(points: np.ndarray, faces: np.ndarray):
    import pyvista as pv

    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    return pv.PolyData(points, cells)


def mode_variation_figure(ssm: SSM, faces: np.ndarray, path: str | Path, n_modes: int = 3,
                          window: tuple[int, int] = (1800, 1200), sds: tuple[float, ...] = (-3.0, 0.0, 3.0)) -> None:
    """Lateral views of mean + w SD of each of the first ``n_modes`` modes, coloured by the distance to
    the mean (mm)."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    n_modes = min(n_modes, ssm.n_modes)
    weights = np.zeros((n_modes * len(sds), ssm.n_modes))
    for i in range(n_modes):
        for j, w in enumerate(sds):
            weights[i * len(sds) + j, i] = w
    shapes = ssm.sample(weights)
    dist = np.linalg.norm(shapes - ssm.mean, axis=-1)
    clim = (0.0, float(dist.max()) or 1.0)
    pl = pv.Plotter(shape=(n_modes, len(sds)), off_screen=True, window_size=list(window), border=False)
    for i in range(n_modes):
        for j, w in enumerate(sds):
            k = i * len(sds) + j
            pl.subplot(i, j)
            mesh = _polydata(shapes[k], faces)
            mesh["distance to mean [mm]"] = dist[k]
            pl.add_mesh(mesh, scalars="distance to mean [mm]", cmap="viridis", clim=clim,
                        show_scalar_bar=(i == 0 and j == len(sds) - 1), smooth_shading=True)
            pl.add_text(f"mode {i + 1}: {w:+.0f} SD", font_size=10)
            pl.view_yz(negative=False)
            pl.reset_camera()
    pl.screenshot(str(path))
    pl.close()
