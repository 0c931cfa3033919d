"""Figures of hex models: the mean model by part (four panels, one a close-up of a disc) and the gallery of
personalized models (the seed's Figure 9)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.cm
import matplotlib.colors
import matplotlib.lines
import numpy as np
import pandas as pd

from spinecohort.figures.canvas import canvas, place_image, px, save
from spinecohort.figures.render import (
    HEX_PART_STYLE,
    SURFACE_STYLE,
    framing,
    ligament_group,
    part_legend_handles,
    render_hex_model,
)


def _to_panel_px(point: np.ndarray, view: str, focal: np.ndarray, scale: float, panel: tuple[int, int]):
    """Pixel (column, row) inside a panel of a point seen by ``view_camera(view, focal, scale)``."""
    across = 1 if view == "lateral" else 0
    sign = 1.0 if view == "lateral" else -1.0  # frontal: +x (patient's right) is on the screen's left
    px_per_mm = panel[1] / (2 * scale)
    col = panel[0] / 2 + sign * (point[across] - focal[across]) * px_per_mm
    row = panel[1] / 2 - (point[2] - focal[2]) * px_per_mm
    return col, row


def _disc_detail_camera(template, points: np.ndarray, disc: str) -> tuple[np.ndarray, float, str]:
    """Focal point and parallel scale (mm) of a close-up of one disc with half of each adjacent body;
    ``disc`` like ``"L4L5"``; falls back to the lowest disc between two vertebrae of the template."""
    discs = [k[2:-3] for k in template.elsets if k.startswith("D_") and k.endswith("_NP") and "S1" not in k]
    if f"D_{disc}_NP" not in template.elsets:
        disc = discs[-1]
    # disc names are <upper><lower> of two level names (e.g. T12L1, L4L5): split before the second letter
    split = next(i for i in range(1, len(disc)) if disc[i].isalpha())
    upper, lower = disc[:split], disc[split:]
    body = {
        lv: points[np.unique(template.hexes[template.elsets[f"V_{lv}_CORE"]])].mean(axis=0) for lv in (upper, lower)
    }
    disc_hexes = np.concatenate(
        [template.elsets.get(f"D_{disc}_{t}", np.zeros(0, np.int64)) for t in ("NP", "AF", "CEP", "RIM")]
    )
    disc_nodes = np.unique(template.hexes[disc_hexes])
    focal = points[disc_nodes].mean(axis=0)
    scale = 0.62 * float(np.linalg.norm(body[upper] - body[lower]))
    return focal, scale, f"{upper}-{lower}"


def part_model_figure(
    template,
    points: np.ndarray,
    path: str | Path,
    size_px: tuple[int, int] = (2400, 1500),
    dpi: int = 150,
    title: str = "Hexahedral mean model by part",
    detail_disc: str = "L4L5",
) -> dict[str, np.ndarray]:
    """One hex model in four panels: lateral view, mid-sagittal section, frontal view (one common scale)
    and a close-up of the mid-sagittal section of one disc with its mesh (``detail_disc``, e.g. ``"L4L5"``,
    where the 0.7 mm cartilage endplates become visible); tissues coloured, surface parts muted, ligaments
    coloured by group; legends of tissues and ligaments.  Writes a PNG of exactly ``size_px`` pixels.

    points: (n_nodes, 3) mm in the template's node order.  Returns the four raw renders by panel name (for
    checks of what is visible)."""
    from matplotlib.patches import Rectangle

    w, h = (int(v) for v in size_px)
    fig = canvas(size_px, dpi)
    title_px, label_px = int(0.05 * h), int(0.035 * h)
    main = (int(0.2 * w), h - title_px - label_px - 10)
    right = w - 3 * main[0] - 20
    detail = (right - 20, min(right - 20, int(0.5 * h)))
    focal, scale = framing(points, "lateral", main)
    focal_f, scale_f = framing(points, "frontal", main)
    scale = max(scale, scale_f)  # one scale for the three whole-model panels: sizes compare across views
    top = title_px + label_px
    panels = {
        "lateral": ("lateral", False, focal, "lateral (from the right)"),
        "section": ("lateral", True, focal, "mid-sagittal section"),
        "frontal": ("frontal", False, focal_f, "frontal (from anterior)"),
    }
    renders = {}
    for k, (name, (view, section, f, label)) in enumerate(panels.items()):
        img = render_hex_model(template, points, view, main, section=section, focal=f, parallel_scale=scale)
        renders[name] = img
        left = 10 + k * main[0]
        place_image(fig, img, left, top)
        fig.text(*px(fig, left + main[0] / 2, title_px + label_px / 2), label, ha="center", va="center", fontsize=9)
    # close-up of one disc, and its frame drawn on the section panel
    d_focal, d_scale, d_name = _disc_detail_camera(template, points, detail_disc)
    d_left = 10 + 3 * main[0] + 10
    renders["detail"] = render_hex_model(
        template, points, "lateral", detail, section=True, edges=True, focal=d_focal, parallel_scale=d_scale
    )
    place_image(fig, renders["detail"], d_left, top)
    fig.text(
        *px(fig, d_left + detail[0] / 2, title_px + label_px / 2),
        f"{d_name} close-up of the section (box), with the mesh",
        ha="center",
        va="center",
        fontsize=9,
    )
    half_w, half_h = d_scale * detail[0] / detail[1], d_scale
    c0, r0 = _to_panel_px(d_focal + np.array([0, -half_w, half_h]), "lateral", focal, scale, main)
    c1, r1 = _to_panel_px(d_focal + np.array([0, half_w, -half_h]), "lateral", focal, scale, main)
    x0, y1 = px(fig, 10 + main[0] + c0, top + r1)
    x1, y0 = px(fig, 10 + main[0] + c1, top + r0)
    fig.add_artist(Rectangle((x0, y1), x1 - x0, y0 - y1, transform=fig.transFigure, fill=False, ec="black", lw=1))
    # scale bar of the whole-model panels
    bar_mm = _scale_bar_mm(scale)
    bar_px = bar_mm / (2 * scale) * main[1]
    y_bar = top + main[1] - 20
    fig.add_artist(
        matplotlib.lines.Line2D(
            [px(fig, 30, 0)[0], px(fig, 30 + bar_px, 0)[0]],
            [px(fig, 0, y_bar)[1]] * 2,
            color="black",
            lw=3,
            transform=fig.transFigure,
        )
    )
    fig.text(*px(fig, 30 + bar_px / 2, y_bar - 8), f"{bar_mm:.0f} mm", ha="center", va="bottom", fontsize=8)
    # legends under the close-up: tissues, then ligament groups
    handles = part_legend_handles(set(ligament_group(template)))
    n_tissue = len(HEX_PART_STYLE) + 1
    y_leg = px(fig, 0, top + detail[1] + 20)[1]
    x_leg = px(fig, d_left, 0)[0]
    leg = fig.legend(
        handles=handles[:n_tissue],
        loc="upper left",
        bbox_to_anchor=(x_leg, y_leg),
        fontsize=8,
        title="tissues and parts",
        title_fontsize=9,
        frameon=False,
        alignment="left",
    )
    fig.add_artist(leg)
    fig.canvas.draw()  # the first legend's extent places the second one under it
    y_lig = leg.get_window_extent().y0 / h - 0.01
    fig.legend(
        handles=handles[n_tissue:],
        loc="upper left",
        bbox_to_anchor=(x_leg, y_lig),
        fontsize=8,
        title="ligaments (spring elements), by group",
        title_fontsize=9,
        frameon=False,
        alignment="left",
    )
    fig.text(*px(fig, w / 2, title_px / 2), title, ha="center", va="center", fontsize=13, weight="bold")
    save(fig, path)
    return renders


def _scale_bar_mm(parallel_scale: float) -> float:
    """A round scale-bar length, about a fifth of the visible height."""
    target = 0.4 * parallel_scale
    return float(min((50, 100, 200, 20, 10), key=lambda v: abs(np.log(v / target))))


def personalized_gallery_figure(
    hex_ssm,
    template,
    table: pd.DataFrame,
    path: str | Path,
    size_px: tuple[int, int] = (3000, 1100),
    dpi: int = 150,
    n_models: int = 10,
    method: str = "fit",
) -> list[str]:
    """The first ``n_models`` personalized hex models side by side, lateral view, one camera for all (so
    posture and size compare), each labelled with its patient ID (the seed's Figure 9).

    table: one row per patient x method with columns ``ID``, ``method`` and ``b1..bk`` (mode weights in SD
    units), optionally ``posture_deg`` (sagittal rotation, ``personalize.parameters.pose``); rows with
    ``method == method`` are used in the table's order.  Returns the IDs shown."""
    if "method" not in table.columns or "ID" not in table.columns:
        raise ValueError("the personalization table needs columns 'ID' and 'method'")
    rows = table[table["method"] == method].head(n_models)
    if rows.empty:
        raise ValueError(f"the personalization table has no row with method == {method!r}")
    wcols = sorted((c for c in table.columns if c[:1] == "b" and c[1:].isdigit()), key=lambda c: int(c[1:]))
    if not wcols:
        raise ValueError("the personalization table has no mode-weight columns b1..bk")
    if len(wcols) > hex_ssm.fields.shape[0]:
        raise ValueError(
            f"the personalization table has {len(wcols)} weights, the hex SSM {hex_ssm.fields.shape[0]} modes"
        )
    weights = rows[wcols].to_numpy(float)
    if not np.all(np.isfinite(weights)):
        raise ValueError("the personalization table has missing or non-finite weights")
    points = hex_ssm.sample(weights)  # (n, n_nodes, 3) mm
    if "posture_deg" in rows.columns:  # the fitted sagittal posture, turned as in the personalized decks
        from spinecohort.personalize.parameters import pose

        points = pose(points, rows["posture_deg"].fillna(0.0).to_numpy(float))
    ids = rows["ID"].astype(str).tolist()

    w, h = (int(v) for v in size_px)
    fig = canvas(size_px, dpi)
    title_px, label_px, legend_px = int(0.07 * h), int(0.05 * h), int(0.08 * h)
    panel = ((w - 20) // len(ids), h - title_px - label_px - legend_px)
    focal, scale = framing(points, "lateral", panel, margin=1.02)
    for k, (pid, pts) in enumerate(zip(ids, points)):
        img = render_hex_model(template, pts, "lateral", panel, ligaments=False, focal=focal, parallel_scale=scale)
        left = 10 + k * panel[0]
        place_image(fig, img, left, title_px + label_px)
        fig.text(
            *px(fig, left + panel[0] / 2, title_px + label_px / 2),
            pid,
            ha="center",
            va="center",
            fontsize=11,
            weight="bold",
        )
    fig.text(
        *px(fig, w / 2, title_px / 2),
        f"Personalized hexahedral models of the first {len(ids)} patients (lateral, anterior to the right, "
        f"common scale; {scale * 2:.0f} mm visible height)",
        ha="center",
        va="center",
        fontsize=12,
    )
    # only what the outside of a model shows: the shell hides the core, the AF the nucleus
    visible = [
        hd
        for hd in part_legend_handles(ligament_groups=())
        if hd.get_label() in (HEX_PART_STYLE["SHELL"][0], HEX_PART_STYLE["AF"][0], SURFACE_STYLE[0])
    ]
    fig.legend(handles=visible, loc="lower center", ncol=3, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.0))
    save(fig, path)
    return ids


# ----------------------------------------------------------------------------------------------------------
# Parameter histograms of the virtual cohort with the patients and the inclusion thresholds
