"""Figures of the statistical shape model: compactness, generalization and specificity, shape-mode
variation."""

from __future__ import annotations

from pathlib import Path

import matplotlib.cm
import matplotlib.colors
import matplotlib.lines
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from spinecohort.figures.canvas import canvas, place_image, px, save
from spinecohort.figures.render import BACKGROUND, framing, view_camera
from spinecohort.ssm.model import SSM


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
    for ax, df, key, title in (
        (axes[0], gen, "generalization", "Generalization (leave-one-out)"),
        (axes[1], spec, "specificity", "Specificity (random samples)"),
    ):
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


def mode_variation_figure(
    ssm: SSM,
    faces: np.ndarray,
    path: str | Path,
    n_modes: int = 3,
    window: tuple[int, int] = (1800, 1200),
    sds: tuple[float, ...] = (-3.0, 0.0, 3.0),
    dpi: int = 150,
) -> None:
    """Lateral views of the mean + w SD of each of the first ``n_modes`` modes (rows) for w in ``sds``
    (columns), coloured by the distance to the mean (mm), one camera and one colour scale for all panels so
    that shapes and colours compare; a PNG of exactly ``window`` = (width, height) pixels."""
    import pyvista as pv

    from spinecohort.mesh.vtk_mesh import surface

    pv.OFF_SCREEN = True
    n_modes = min(n_modes, ssm.n_modes)
    weights = np.zeros((n_modes * len(sds), ssm.n_modes))
    for i in range(n_modes):
        for j, w in enumerate(sds):
            weights[i * len(sds) + j, i] = w
    shapes = ssm.sample(weights)
    dist = np.linalg.norm(shapes - ssm.mean, axis=-1)
    vmax = float(dist.max()) or 1.0

    W, H = (int(v) for v in window)
    fig = canvas(window, dpi)
    title_px, header_px, label_px, cbar_px = int(0.06 * H), int(0.04 * H), int(0.04 * W), int(0.11 * W)
    panel = ((W - label_px - cbar_px) // len(sds), (H - title_px - header_px) // n_modes)
    focal, scale = framing(shapes, "lateral", panel, margin=1.03)
    pl = pv.Plotter(off_screen=True, window_size=list(panel))
    pl.set_background(BACKGROUND)
    mesh = surface(shapes[0], faces)
    mesh["distance to mean [mm]"] = dist[0]
    pl.add_mesh(
        mesh,
        scalars="distance to mean [mm]",
        cmap="viridis",
        clim=(0.0, vmax),
        show_scalar_bar=False,
        smooth_shading=True,
    )
    view_camera(pl, "lateral", focal, scale)
    ev = ssm.explained_variance_ratio
    for i in range(n_modes):
        y0 = title_px + header_px + i * panel[1]
        fig.text(
            *px(fig, label_px / 2, y0 + panel[1] / 2),
            f"mode {i + 1} ({100 * ev[i]:.1f} % of variance)",
            rotation=90,
            ha="center",
            va="center",
            fontsize=9,
        )
        for j, _w in enumerate(sds):
            k = i * len(sds) + j
            mesh.points = shapes[k]
            mesh["distance to mean [mm]"] = dist[k]
            pl.render()
            place_image(fig, np.asarray(pl.screenshot(return_img=True))[..., :3], label_px + j * panel[0], y0)
    for j, w in enumerate(sds):
        fig.text(
            *px(fig, label_px + (j + 0.5) * panel[0], title_px + header_px / 2),
            "mean" if w == 0 else f"{w:+g} SD",
            ha="center",
            va="center",
            fontsize=10,
        )
    pl.close()
    cax = fig.add_axes([(W - 0.6 * cbar_px) / W, 0.15, 0.15 * cbar_px / W, 0.6])
    fig.colorbar(
        matplotlib.cm.ScalarMappable(matplotlib.colors.Normalize(0, vmax), "viridis"),
        cax=cax,
        label="distance to the mean shape [mm]",
    )
    fig.text(
        *px(fig, W / 2, title_px / 2),
        "SSM shape modes (lateral, anterior to the right, common scale)",
        ha="center",
        va="center",
        fontsize=12,
        weight="bold",
    )
    save(fig, path)


# ----------------------------------------------------------------------------------------------------------
# Canvas helpers: every figure is exactly the configured size in pixels
