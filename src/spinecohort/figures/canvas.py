"""The canvas of every figure: a matplotlib figure of exactly the configured size in pixels, renders placed
onto it pixel for pixel."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np


def canvas(size_px: tuple[int, int], dpi: int):
    """A matplotlib figure of exactly ``size_px`` = (width, height) pixels at ``dpi``."""
    w, h = (int(v) for v in size_px)
    return plt.figure(figsize=(w / dpi, h / dpi), dpi=dpi)


def save(fig, path: str | Path) -> None:
    # no bbox_inches="tight": it would change the pixel size the config states
    fig.savefig(path, dpi=fig.dpi, facecolor="white")
    plt.close(fig)


def place_image(fig, img: np.ndarray, left_px: int, top_px: int) -> None:
    """Put a rendered image onto the canvas pixel for pixel (no resampling), its top-left corner at
    (left_px, top_px) counted from the canvas' top-left."""
    h_fig = int(round(fig.get_figheight() * fig.dpi))
    fig.figimage(img, xo=left_px, yo=h_fig - top_px - img.shape[0], origin="upper")


def px(fig, x_px: float, y_px: float) -> tuple[float, float]:
    """Figure coordinates of a pixel position counted from the top-left."""
    w, h = fig.get_figwidth() * fig.dpi, fig.get_figheight() * fig.dpi
    return x_px / w, 1.0 - y_px / h
