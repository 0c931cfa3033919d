"""Figures a person would rather look at than read.

Charts (matplotlib): SSM compactness and quality curves, histograms of the virtual cohort's spinopelvic
parameters with the patients and the inclusion thresholds, and a mesh-quality summary.  Renders (pyvista,
off-screen; VTK falls back to EGL/OSMesa software rendering without a display): shape-mode variation, the hex
mean model coloured by tissue with its ligaments, and a gallery of personalized models.

Every figure is written at exactly the pixel size it is given (no tight bounding box); 3-D renders are
placed onto the canvas pixel for pixel.  Views: lateral = from the patient's right (+x in the RAS frame of
``landmarks``), anterior to the right; frontal = from anterior (+y), z up; parallel projection.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.cm  # noqa: E402
import matplotlib.colors  # noqa: E402
import matplotlib.lines  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from spinecohort.ssm.model import SSM  # noqa: E402


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
    fig = _canvas(window, dpi)
    title_px, header_px, label_px, cbar_px = int(0.06 * H), int(0.04 * H), int(0.04 * W), int(0.11 * W)
    panel = ((W - label_px - cbar_px) // len(sds), (H - title_px - header_px) // n_modes)
    focal, scale = _framing(shapes, "lateral", panel, margin=1.03)
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
    _view_camera(pl, "lateral", focal, scale)
    ev = ssm.explained_variance_ratio
    for i in range(n_modes):
        y0 = title_px + header_px + i * panel[1]
        fig.text(
            *_px(fig, label_px / 2, y0 + panel[1] / 2),
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
            _place_image(fig, np.asarray(pl.screenshot(return_img=True))[..., :3], label_px + j * panel[0], y0)
    for j, w in enumerate(sds):
        fig.text(
            *_px(fig, label_px + (j + 0.5) * panel[0], title_px + header_px / 2),
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
        *_px(fig, W / 2, title_px / 2),
        "SSM shape modes (lateral, anterior to the right, common scale)",
        ha="center",
        va="center",
        fontsize=12,
        weight="bold",
    )
    _save(fig, path)


# ----------------------------------------------------------------------------------------------------------
# Canvas helpers: every figure is exactly the configured size in pixels


def _canvas(size_px: tuple[int, int], dpi: int):
    """A matplotlib figure of exactly ``size_px`` = (width, height) pixels at ``dpi``."""
    w, h = (int(v) for v in size_px)
    return plt.figure(figsize=(w / dpi, h / dpi), dpi=dpi)


def _save(fig, path: str | Path) -> None:
    # no bbox_inches="tight": it would change the pixel size the config states
    fig.savefig(path, dpi=fig.dpi, facecolor="white")
    plt.close(fig)


def _place_image(fig, img: np.ndarray, left_px: int, top_px: int) -> None:
    """Put a rendered image onto the canvas pixel for pixel (no resampling), its top-left corner at
    (left_px, top_px) counted from the canvas' top-left."""
    h_fig = int(round(fig.get_figheight() * fig.dpi))
    fig.figimage(img, xo=left_px, yo=h_fig - top_px - img.shape[0], origin="upper")


def _px(fig, x_px: float, y_px: float) -> tuple[float, float]:
    """Figure coordinates of a pixel position counted from the top-left."""
    w, h = fig.get_figwidth() * fig.dpi, fig.get_figheight() * fig.dpi
    return x_px / w, 1.0 - y_px / h


# ----------------------------------------------------------------------------------------------------------
# The hex model coloured by part

#: hex tissue -> (legend label, colour); the tissue is the suffix of the template's element set name.
HEX_PART_STYLE: dict[str, tuple[str, str]] = {
    "CORE": ("vertebral body: cancellous core", "#ead7a4"),
    "SHELL": ("vertebral body: cortical shell", "#9c7a35"),
    "NP": ("disc: nucleus pulposus (NP)", "#d7301f"),
    "AF": ("disc: annulus fibrosus (AF)", "#2b6cb0"),
    "CEP": ("disc: cartilage endplate (CEP)", "#2ca25f"),
}
#: the S3 surface parts (posterior elements, sacrum, pelvis, femoral heads): one muted colour
SURFACE_STYLE: tuple[str, str] = ("posterior elements, sacrum, pelvis, femoral heads (S3)", "#c8c8c8")
#: ligament group -> (legend label, colour); drawn unlit, so the colour on screen is exactly this one
LIGAMENT_STYLE: dict[str, tuple[str, str]] = {
    "ALL": ("anterior longitudinal lig. (ALL)", "#6a3d9a"),
    "PLL": ("posterior longitudinal lig. (PLL)", "#ff7f00"),
    "ISL": ("interspinous lig. (ISL)", "#00b5c9"),
    "SSL": ("supraspinous lig. (SSL)", "#e7298a"),
    "LF": ("ligamentum flavum (LF)", "#808000"),
    "CL": ("capsular lig. (CL)", "#111111"),
    "ITL": ("intertransverse lig. (ITL)", "#b15928"),
}
BACKGROUND = "white"

# the six faces of a VTK / C3D8 hexahedron, outward for a positively oriented element
_HEX_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])


def hex_tissue(template) -> np.ndarray:
    """(E,) tissue of every hex: a key of ``HEX_PART_STYLE`` (the suffix of its element set's name; the annulus'
    rim insertion ``_RIM`` drawn as annulus)."""
    from spinecohort.mesh.template import set_tissue

    out = np.full(len(template.hexes), "", dtype=object)
    for name, idx in template.elsets.items():
        if template.elset_kind[name] == "hex":
            out[idx] = set_tissue(name)
    if np.any(out == ""):
        raise ValueError("the template has hexes outside every element set")
    return out.astype(str)


def ligament_group(template) -> np.ndarray:
    """(L,) ligament group of every 2-node element (``LIG_<group>`` sets)."""
    out = np.full(len(template.ligaments), "", dtype=object)
    for name, idx in template.elsets.items():
        if template.elset_kind[name] == "lig":
            out[idx] = name[len("LIG_") :]
    return out.astype(str)


def hex_boundary_faces(hexes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quads on the boundary of a set of hexahedra: the faces that belong to exactly one of them.

    hexes: (E, 8) node ids.  Returns faces (F, 4) node ids, outward for positively oriented hexes, and
    owner (F,) the index of the hex each face belongs to.  Interior faces (shared by two hexes) are
    dropped, so a section through the mesh shows the tissues on its cut face and nothing is drawn twice.
    """
    hexes = np.asarray(hexes)
    faces = hexes[:, _HEX_FACES].reshape(-1, 4)
    owner = np.repeat(np.arange(len(hexes)), 6)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    return faces[once], owner[once]


def _section_side(template, points: np.ndarray, axis: int) -> tuple[np.ndarray, float]:
    """Which hexes lie on the far side of each cross-section's own mid-plane along ``axis`` (0: lateral
    x, 1: anterior y), and the global mid-plane coordinate for the surface parts.

    Hexes are cut by their O-grid cross-section coordinate, so every body and disc is halved through its
    own centre even where the column curves; returns (keep (E,) bool for a camera on the + side, plane)."""
    nq = len(template.grid.quads)
    local = template.grid.nodes[template.grid.quads].mean(axis=1)[np.arange(len(template.hexes)) % nq]
    centroid = points[template.hexes].mean(axis=1)
    # the O-grid axes follow the endplate frames (lateral hint +x): orient them with the global axis
    sign = np.sign(np.corrcoef(local[:, axis], centroid[:, axis])[0, 1]) or 1.0
    keep = sign * local[:, axis] < 0
    return keep, float(np.median(points[: template.n_hex_nodes, axis]))


def _view_camera(plotter, view: str, focal: np.ndarray, parallel_scale: float) -> None:
    """Parallel projection; 'lateral' looks from the patient's right (+x, anterior on the right),
    'frontal' from anterior (+y, the patient's right on the left); z up."""
    direction = {"lateral": np.array([1.0, 0, 0]), "frontal": np.array([0, 1.0, 0])}[view]
    plotter.enable_parallel_projection()
    plotter.camera.focal_point = tuple(focal)
    plotter.camera.position = tuple(focal + 2000.0 * direction)
    plotter.camera.up = (0.0, 0.0, 1.0)
    plotter.camera.parallel_scale = parallel_scale
    plotter.camera.clipping_range = (1.0, 5000.0)


def _framing(points: np.ndarray, view: str, size_px: tuple[int, int], margin: float = 1.04):
    """Focal point and parallel scale (half the visible height, mm) that fit ``points`` (.., N, 3) into a
    (width, height) pixel viewport for the given view."""
    p = np.asarray(points).reshape(-1, 3)
    lo, hi = p.min(0), p.max(0)
    across = 1 if view == "lateral" else 0
    aspect = size_px[0] / size_px[1]
    scale = margin * max((hi[2] - lo[2]) / 2, (hi[across] - lo[across]) / 2 / aspect)
    return (lo + hi) / 2, scale


def render_hex_model(
    template,
    points: np.ndarray,
    view: str,
    size_px: tuple[int, int],
    section: bool = False,
    ligaments: bool = True,
    edges: bool = False,
    focal=None,
    parallel_scale=None,
) -> np.ndarray:
    """Off-screen render (H, W, 3 uint8) of a hex model coloured by tissue, its surface parts muted and
    its ligaments as lines coloured by group.

    points: (n_nodes, 3) mm in the template's node order (``HexSSM.sample``).  view: 'lateral' | 'frontal'.
    section: cut every body and disc through its own mid-plane (lateral: mid-sagittal, frontal:
    mid-coronal) and keep the far half, to show the nucleus, shell and endplates; surface parts and
    bilateral ligaments are cut by the model's mid-plane.  focal/parallel_scale: a fixed camera (mm), e.g.
    shared by the panels of a gallery; default: fit this model.  edges: draw the element edges (for
    close-ups; at whole-spine scale they would hide the colours).
    """
    import pyvista as pv

    from spinecohort.mesh.vtk_mesh import polylines, surface

    pv.OFF_SCREEN = True
    points = np.asarray(points, dtype=np.float64)
    axis = 0 if view == "lateral" else 1
    hexes, tris, ligs = template.hexes, template.tris, template.ligaments
    tissue, group = hex_tissue(template), ligament_group(template)
    if section:
        keep, plane = _section_side(template, points, axis)
        hexes, tissue = hexes[keep], tissue[keep]
        tris = tris[points[tris].mean(axis=1)[:, axis] < plane]
        # midline ligaments (ALL, PLL, SSL, ISL) lie in the cut plane: keep them and the far bilateral ones
        far = points[ligs].max(axis=1)[:, axis] < plane + 3.0
        ligs, group = ligs[far], group[far]
    if focal is None or parallel_scale is None:
        focal, parallel_scale = _framing(points, view, size_px)

    faces, owner = hex_boundary_faces(hexes)
    rgb = np.array([matplotlib.colors.to_rgb(HEX_PART_STYLE[t][1]) for t in HEX_PART_STYLE])
    tissue_index = {t: i for i, t in enumerate(HEX_PART_STYLE)}
    face_rgb = (255 * rgb[np.array([tissue_index[t] for t in tissue])[owner]]).astype(np.uint8)
    column = surface(points, faces)
    column.cell_data["rgb"] = face_rgb

    pl = pv.Plotter(off_screen=True, window_size=[int(size_px[0]), int(size_px[1])])
    pl.set_background(BACKGROUND)
    pl.add_mesh(
        column,
        scalars="rgb",
        rgb=True,
        show_edges=edges,
        edge_color="#4d4d4d",
        line_width=1,
        ambient=0.25,
        diffuse=0.75,
        specular=0.0,
    )
    if len(tris):
        surf = surface(points, tris)
        pl.add_mesh(surf, color=SURFACE_STYLE[1], ambient=0.3, diffuse=0.7, specular=0.0, smooth_shading=True)
    if ligaments and len(ligs):
        # lines are drawn unlit (exact group colour). The lateral whole-model view draws them on an overlay
        # layer in front of the bones: the capsular ligaments lie inside the facet joints and would otherwise
        # be hidden. A section keeps depth (only far-side and midline lines are left) and moves them 2 mm
        # towards the camera, so that the midline ones are not hidden in the cut face they lie on.
        shift = np.zeros(3)
        target = pl.renderer
        if section:
            shift[axis] = 2.0
        elif view == "lateral":
            import vtk

            target = vtk.vtkRenderer()
            target.SetLayer(1)
            target.SetActiveCamera(pl.renderer.GetActiveCamera())
            pl.ren_win.SetNumberOfLayers(2)
            pl.ren_win.AddRenderer(target)
        for g, (_, colour) in LIGAMENT_STYLE.items():
            sel = ligs[group == g]
            if len(sel):
                lines = polylines(points + shift, sel)
                actor = pv.Actor(mapper=pv.DataSetMapper(lines))
                actor.prop.color, actor.prop.line_width, actor.prop.lighting = colour, 4, False
                target.AddActor(actor)
    _view_camera(pl, view, np.asarray(focal, float), float(parallel_scale))
    img = pl.screenshot(return_img=True)
    pl.close()
    return np.asarray(img)[..., :3]


def _part_legend_handles(ligament_groups=None):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=c, edgecolor="#555555", label=label) for label, c in HEX_PART_STYLE.values()]
    handles.append(Patch(facecolor=SURFACE_STYLE[1], edgecolor="#555555", label=SURFACE_STYLE[0]))
    for g, (label, c) in LIGAMENT_STYLE.items():
        if ligament_groups is None or g in ligament_groups:
            handles.append(Line2D([0], [0], color=c, lw=3, label=label))
    return handles


def _to_panel_px(point: np.ndarray, view: str, focal: np.ndarray, scale: float, panel: tuple[int, int]):
    """Pixel (column, row) inside a panel of a point seen by ``_view_camera(view, focal, scale)``."""
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
    fig = _canvas(size_px, dpi)
    title_px, label_px = int(0.05 * h), int(0.035 * h)
    main = (int(0.2 * w), h - title_px - label_px - 10)
    right = w - 3 * main[0] - 20
    detail = (right - 20, min(right - 20, int(0.5 * h)))
    focal, scale = _framing(points, "lateral", main)
    focal_f, scale_f = _framing(points, "frontal", main)
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
        _place_image(fig, img, left, top)
        fig.text(*_px(fig, left + main[0] / 2, title_px + label_px / 2), label, ha="center", va="center", fontsize=9)
    # close-up of one disc, and its frame drawn on the section panel
    d_focal, d_scale, d_name = _disc_detail_camera(template, points, detail_disc)
    d_left = 10 + 3 * main[0] + 10
    renders["detail"] = render_hex_model(
        template, points, "lateral", detail, section=True, edges=True, focal=d_focal, parallel_scale=d_scale
    )
    _place_image(fig, renders["detail"], d_left, top)
    fig.text(
        *_px(fig, d_left + detail[0] / 2, title_px + label_px / 2),
        f"{d_name} close-up of the section (box), with the mesh",
        ha="center",
        va="center",
        fontsize=9,
    )
    half_w, half_h = d_scale * detail[0] / detail[1], d_scale
    c0, r0 = _to_panel_px(d_focal + np.array([0, -half_w, half_h]), "lateral", focal, scale, main)
    c1, r1 = _to_panel_px(d_focal + np.array([0, half_w, -half_h]), "lateral", focal, scale, main)
    x0, y1 = _px(fig, 10 + main[0] + c0, top + r1)
    x1, y0 = _px(fig, 10 + main[0] + c1, top + r0)
    fig.add_artist(Rectangle((x0, y1), x1 - x0, y0 - y1, transform=fig.transFigure, fill=False, ec="black", lw=1))
    # scale bar of the whole-model panels
    bar_mm = _scale_bar_mm(scale)
    bar_px = bar_mm / (2 * scale) * main[1]
    y_bar = top + main[1] - 20
    fig.add_artist(
        matplotlib.lines.Line2D(
            [_px(fig, 30, 0)[0], _px(fig, 30 + bar_px, 0)[0]],
            [_px(fig, 0, y_bar)[1]] * 2,
            color="black",
            lw=3,
            transform=fig.transFigure,
        )
    )
    fig.text(*_px(fig, 30 + bar_px / 2, y_bar - 8), f"{bar_mm:.0f} mm", ha="center", va="bottom", fontsize=8)
    # legends under the close-up: tissues, then ligament groups
    handles = _part_legend_handles(set(ligament_group(template)))
    n_tissue = len(HEX_PART_STYLE) + 1
    y_leg = _px(fig, 0, top + detail[1] + 20)[1]
    x_leg = _px(fig, d_left, 0)[0]
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
    fig.text(*_px(fig, w / 2, title_px / 2), title, ha="center", va="center", fontsize=13, weight="bold")
    _save(fig, path)
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
    units), optionally ``posture_deg`` (sagittal rotation, ``personalize.pose``); rows with
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
        from spinecohort.personalize import pose

        points = pose(points, rows["posture_deg"].fillna(0.0).to_numpy(float))
    ids = rows["ID"].astype(str).tolist()

    w, h = (int(v) for v in size_px)
    fig = _canvas(size_px, dpi)
    title_px, label_px, legend_px = int(0.07 * h), int(0.05 * h), int(0.08 * h)
    panel = ((w - 20) // len(ids), h - title_px - label_px - legend_px)
    focal, scale = _framing(points, "lateral", panel, margin=1.02)
    for k, (pid, pts) in enumerate(zip(ids, points)):
        img = render_hex_model(template, pts, "lateral", panel, ligaments=False, focal=focal, parallel_scale=scale)
        left = 10 + k * panel[0]
        _place_image(fig, img, left, title_px + label_px)
        fig.text(
            *_px(fig, left + panel[0] / 2, title_px + label_px / 2),
            pid,
            ha="center",
            va="center",
            fontsize=11,
            weight="bold",
        )
    fig.text(
        *_px(fig, w / 2, title_px / 2),
        f"Personalized hexahedral models of the first {len(ids)} patients (lateral, anterior to the right, "
        f"common scale; {scale * 2:.0f} mm visible height)",
        ha="center",
        va="center",
        fontsize=12,
    )
    # only what the outside of a model shows: the shell hides the core, the AF the nucleus
    visible = [
        hd
        for hd in _part_legend_handles(ligament_groups=())
        if hd.get_label() in (HEX_PART_STYLE["SHELL"][0], HEX_PART_STYLE["AF"][0], SURFACE_STYLE[0])
    ]
    fig.legend(handles=visible, loc="lower center", ncol=3, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.0))
    _save(fig, path)
    return ids


# ----------------------------------------------------------------------------------------------------------
# Parameter histograms of the virtual cohort with the patients and the inclusion thresholds

#: config key of an inclusion criterion (``synthetic.criteria``) -> the parameter column it bounds from below
CRITERIA_COLUMNS: dict[str, str] = {"PI_minus_LL_min_deg": "PI_minus_LL", "PT_min_deg": "PT", "SVA_T1_min_mm": "SVA_T1"}

PARAMETER_LABELS: dict[str, str] = {
    "PI": "pelvic incidence PI",
    "PT": "pelvic tilt PT",
    "SS": "sacral slope SS",
    "LL": "lumbar lordosis LL (L1-S1)",
    "LL_L4S1": "lower lumbar lordosis L4-S1",
    "LL_L1L5": "lordosis L1-L5",
    "PI_minus_LL": "PI - LL mismatch",
    "TPA": "T1 pelvic angle TPA",
    "T1SPI": "T1 spinopelvic inclination",
    "GT": "global tilt GT",
    "TK_T1T12": "kyphosis T1-T12",
    "TK_T4T12": "thoracic kyphosis T4-T12",
    "TK_T5T12": "kyphosis T5-T12",
    "Cobb": "main coronal Cobb angle",
    "SVA_T1": "T1 sagittal offset (SVA proxy)",
    "SVA_C7est": "SVA, C7 estimated",
    "RPV": "relative pelvic version RPV",
    "RLL": "relative lumbar lordosis RLL",
    "RSA": "relative spinopelvic alignment RSA",
    "LDI": "lordosis distribution index LDI",
    "GAP_assumed_age": "GAP score (assumed age)",
    "GAP_noage": "GAP score without age",
}


def parameter_histograms_figure(
    virtual: pd.DataFrame,
    patients: pd.DataFrame,
    criteria: dict[str, float],
    parameters: list[str],
    path: str | Path,
    size_px: tuple[int, int] = (2000, 1400),
    dpi: int = 150,
    units: dict[str, str] | None = None,
) -> pd.DataFrame:
    """Histogram per parameter of the virtual cohort (density) with the patients' histogram overlaid and the
    inclusion thresholds (``criteria``: keys of ``CRITERIA_COLUMNS``, lower bounds) marked.

    virtual, patients: parameter tables (column names as in ``measure``, e.g. ``PI``, ``PI_minus_LL``).
    Returns the share (%) of virtual models and patients above each threshold (one row per criterion)."""
    from spinecohort.measure.spinopelvic import UNITS

    units = UNITS if units is None else units
    for name, table in (("virtual cohort", virtual), ("patients", patients)):
        missing = [p for p in parameters if p not in table.columns]
        if missing:
            raise ValueError(f"the {name} table has no column(s) {missing}")
    unknown = set(criteria) - set(CRITERIA_COLUMNS)
    if unknown:
        raise ValueError(f"unknown inclusion criteria {sorted(unknown)}; known: {sorted(CRITERIA_COLUMNS)}")
    thresholds = {CRITERIA_COLUMNS[k]: float(v) for k, v in criteria.items()}
    n = len(parameters)
    ncols = 4 if n > 9 else 3 if n > 4 else n
    nrows = int(np.ceil(n / ncols))
    fig = _canvas(size_px, dpi)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    shares = []
    for ax, p in zip(axes, parameters):
        v = virtual[p].to_numpy(float)
        q = patients[p].to_numpy(float)
        v, q = v[np.isfinite(v)], q[np.isfinite(q)]
        both = np.concatenate([v, q])
        lo, hi = (both.min(), both.max()) if both.size else (0.0, 1.0)
        if p in thresholds:
            lo, hi = min(lo, thresholds[p]), max(hi, thresholds[p])
        pad = 0.03 * (hi - lo or 1.0)
        edges = np.linspace(lo - pad, hi + pad, 41)
        ax.hist(v, bins=edges, density=True, color="#8fb3d9", label=f"virtual models (n = {v.size:,})")
        ax.hist(
            q, bins=edges[::4], density=True, histtype="step", color="#1f2d3d", lw=1.6, label=f"patients (n = {q.size})"
        )
        unit = units.get(p, "")
        if p in thresholds:
            t = thresholds[p]
            ax.axvspan(edges[0], t, color="#c0392b", alpha=0.08, lw=0)
            ax.axvline(t, color="#c0392b", ls="--", lw=1.4)
            sv, sq = 100 * np.mean(v > t) if v.size else np.nan, 100 * np.mean(q > t) if q.size else np.nan
            shares.append(
                {"parameter": p, "threshold": t, "unit": unit, "pct_virtual_above": sv, "pct_patients_above": sq}
            )
            ax.set_title(
                f"inclusion > {t:g} {unit}: virtual {sv:.0f} %, patients {sq:.0f} %", fontsize=8, color="#c0392b"
            )
        ax.set_xlim(edges[0], edges[-1])
        ax.set_xlabel(f"{PARAMETER_LABELS.get(p, p)} [{unit}]" if unit else PARAMETER_LABELS.get(p, p), fontsize=8)
        ax.set_ylabel(f"density [1/{unit}]" if unit else "density", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes[n:]:
        ax.set_visible(False)
    handles, labels = axes[0].get_legend_handles_labels()
    from matplotlib.patches import Patch

    handles.append(Patch(facecolor="#c0392b", alpha=0.25, label="excluded by an inclusion criterion"))
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    all_in = np.ones(len(virtual), bool)
    for p, t in thresholds.items():
        all_in &= virtual[p].to_numpy(float) > t
    crit = ", ".join(f"{p.replace('_minus_', ' - ')} > {t:g} {units.get(p, '')}" for p, t in thresholds.items())
    fig.suptitle(
        f"Spinopelvic parameters of the virtual cohort and the patients\n"
        f"{100 * all_in.mean():.1f} % of the virtual models meet every inclusion criterion ({crit})",
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.95))
    _save(fig, path)
    return pd.DataFrame(shares)


# ----------------------------------------------------------------------------------------------------------
# Mesh-quality summary of the virtual cohort and the mean model


def quality_summary_figure(
    quality: pd.DataFrame,
    table3: pd.DataFrame,
    path: str | Path,
    size_px: tuple[int, int] = (1800, 1300),
    dpi: int = 150,
) -> None:
    """Four panels: the per-model minimum scaled Jacobian before and after repair; its distribution per
    tissue (after repair); the share of models with inverted hexes before repair, repaired, and left; and the
    seed's Table 3 indicators of the mean model per tissue.

    quality: the shards' quality tables concatenated (``min_sj_before``, ``min_sj_after``, ``invalid_before``,
    ``invalid_after``, ``repaired``, ``min_sj_<tissue>``).  table3: ``results/template/mean_quality.csv``."""
    need = {"min_sj_before", "min_sj_after", "invalid_before", "invalid_after", "repaired"}
    if need - set(quality.columns):
        raise ValueError(f"the quality table lacks columns {sorted(need - set(quality.columns))}")
    need3 = {
        "part",
        "pct_errors",
        "pct_warnings",
        "pct_edge_ratio_gt_10",
        "pct_max_face_angle_gt_160",
        "nodal_jacobian_ratio_min",
    }
    if need3 - set(table3.columns):
        raise ValueError(f"the Table 3 summary lacks columns {sorted(need3 - set(table3.columns))}")
    n = len(quality)
    fig = _canvas(size_px, dpi)
    (a, b), (c, d) = fig.subplots(2, 2)

    lo = min(quality["min_sj_before"].min(), quality["min_sj_after"].min(), 0.0)
    edges = np.linspace(lo - 0.02, 1.0, 52)
    a.hist(quality["min_sj_before"], bins=edges, color="#8fb3d9", label="before repair")
    a.hist(quality["min_sj_after"], bins=edges, histtype="step", color="#1f2d3d", lw=1.5, label="after repair")
    a.axvline(0.0, color="#c0392b", lw=1.2, label="inverted (<= 0)")
    a.axvline(0.2, color="#e67e22", ls="--", lw=1.2, label="warning (< 0.2)")
    a.set_xlabel("minimum scaled Jacobian of a model [-]")
    a.set_ylabel("models")
    a.set_title(f"Worst element per model (n = {n:,} models)", fontsize=10)
    a.legend(fontsize=7)

    tissue_cols = [col for col in quality.columns if col.startswith("min_sj_") and col not in need]
    if tissue_cols:
        b.boxplot(
            [quality[col].dropna().to_numpy() for col in tissue_cols],
            whis=(0, 100),
            tick_labels=[col[len("min_sj_") :] for col in tissue_cols],
        )
        b.axhline(0.0, color="#c0392b", lw=1.2)
        b.axhline(0.2, color="#e67e22", ls="--", lw=1.2)
    b.set_xlabel("tissue")
    b.set_ylabel("minimum scaled Jacobian per model [-]")
    b.set_title("Worst element per model and tissue (after repair; whiskers: min-max)", fontsize=10)

    before = int((quality["invalid_before"] > 0).sum())
    repaired = int(((quality["invalid_before"] > 0) & (quality["invalid_after"] == 0)).sum())
    left = int((quality["invalid_after"] > 0).sum())
    counts = [before, repaired, left]
    bars = c.bar(
        ["inverted hexes\nbefore repair", "repaired", "inverted hexes\nafter repair"],
        [100 * k / max(n, 1) for k in counts],
        color=["#8fb3d9", "#2ca25f", "#c0392b"],
    )
    for bar, k in zip(bars, counts):
        c.text(
            bar.get_x() + bar.get_width() / 2,
            bar.get_height(),
            f"{k:,} model{'s' if k != 1 else ''}",
            ha="center",
            va="bottom",
            fontsize=8,
        )
    n_before, n_after = int(quality["invalid_before"].sum()), int(quality["invalid_after"].sum())
    left_txt = (
        f"inverted hexes: {n_before:,} before, {n_after:,} after repair" if n_before else "no inverted hex in any model"
    )
    c.set_ylabel("share of the virtual models [%]")
    c.set_ylim(0, max(1.0, 1.25 * max(100 * k / max(n, 1) for k in counts)))
    c.set_title(f"Models with inverted hexes ({left_txt})", fontsize=10)

    t3 = table3.set_index("part")
    cols = [
        ("pct_errors", "errors (sJ <= 0)"),
        ("pct_warnings", "warnings (sJ < 0.2 or face angle)"),
        ("pct_edge_ratio_gt_10", "edge ratio > 10"),
        ("pct_max_face_angle_gt_160", "face angle > 160 deg"),
    ]
    x = np.arange(len(t3))
    width = 0.8 / len(cols)
    for k, (col, label) in enumerate(cols):
        bars = d.bar(x + (k - (len(cols) - 1) / 2) * width, t3[col], width, label=label)
        d.bar_label(bars, fmt="%.1f", fontsize=6)
    d.set_xticks(x, [f"{p}\n(Jr min {t3.loc[p, 'nodal_jacobian_ratio_min']:.2f})" for p in t3.index], fontsize=8)
    d.set_ylabel("share of elements [%]")
    d.set_title("Table 3 indicators of the hex mean model per tissue (Jr: nodal Jacobian ratio)", fontsize=10)
    d.legend(fontsize=7)
    for ax in (a, b, c, d):
        ax.grid(alpha=0.3, axis="y")
        ax.tick_params(labelsize=8)
    fig.suptitle("Hexahedral mesh quality of the virtual cohort", fontsize=12)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    _save(fig, path)


def validation_figure(validation: pd.DataFrame, path: str | Path, title: str = "") -> Path:
    """The seed's Figures 10-11 for our model: ROM bars (`spinecohort.rom.compare.validate` table), the
    accepted in-vitro interval as whiskers; one panel per extraction mode."""
    modes = [m for m in ("lumbar", "unit") if (validation["mode"] == m).any()]
    fig, axes = plt.subplots(
        len(modes), 1, figsize=(max(6, 0.6 * len(validation) + 3), 3.6 * len(modes)), squeeze=False
    )
    for ax, mode in zip(axes[:, 0], modes):
        v = validation[validation["mode"] == mode].reset_index(drop=True)
        x = np.arange(len(v))
        colors = ["tab:green" if r is True else ("tab:red" if r is False else "tab:gray") for r in v["in_range"]]
        ax.bar(x, v["model_deg"], color=colors, alpha=0.7, label="model (green: in range, red: out)")
        # whiskers: the calibration criterion's accepted interval (mean +- acceptance_sd SD, or the range
        # corrected for the missing rib heads; spinecohort.rom.compare)
        lo, hi = v["accept_low"].astype(float), v["accept_high"].astype(float)
        centre = np.where(v["ref_statistic"] == "mean_sd", v["ref_value"].astype(float), 0.5 * (lo + hi))
        ax.errorbar(
            x + 0.25,
            centre,
            yerr=[centre - lo, hi - centre],
            fmt="o",
            color="k",
            capsize=4,
            label="in vitro: accepted interval",
        )
        ax.set_xticks(
            x,
            [f"{s}\n{m.replace('_', ' ')}\n({sd})" for s, m, sd in zip(v["segment"], v["motion"], v["side"])],
            fontsize=7,
        )
        ax.set_ylabel("ROM (deg)")
        ax.set_title(f"{title} {'lumbar model (pelvis..T10)' if mode == 'lumbar' else 'functional units'}".strip())
        ax.legend(fontsize=7, loc="upper left")  # the right end holds the tallest bars (axial rotation)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)


def rom_modes_figure(modes: pd.DataFrame, path: str | Path) -> Path:
    """Segmental ROM vs shape-mode weight (`spinecohort.rom.modes.gather` table): one row of panels per
    motion plane (full range, both directions summed), one column per segment and extraction; one line per
    shape mode, through the mean at weight 0.  Open markers: a case short of the full moment."""
    from spinecohort.rom.deck import PLANES

    cols = modes[["mode", "segment"]].drop_duplicates().sort_values(["mode", "segment"], key=_segment_key)
    fig, axes = plt.subplots(
        len(PLANES), len(cols), figsize=(1.9 * len(cols) + 1, 2.2 * len(PLANES)), squeeze=False, sharex=True
    )
    colours = plt.get_cmap("tab10")
    for r, (plane, cases) in enumerate(PLANES.items()):
        for c, (mode, seg) in enumerate(cols.itertuples(index=False)):
            ax = axes[r, c]
            d = modes[(modes["mode"] == mode) & (modes["segment"] == seg) & modes["load_case"].isin(cases)]
            full = d.groupby(["shape_mode", "weight_sd"]).agg(rom=("rom_deg", "sum"), frac=("load_fraction", "min"))
            for k, (sm, g) in enumerate(full.groupby(level=0)):
                g = g.droplevel(0).sort_index()
                ax.plot(g.index, g["rom"], "-", color=colours(k), label=f"mode {sm}")
                short = g["frac"] < 1.0 - 1e-6
                ax.plot(g.index[~short], g["rom"][~short], "o", color=colours(k), ms=3)
                ax.plot(g.index[short], g["rom"][short], "o", mfc="none", color=colours(k), ms=5)
            if r == 0:
                ax.set_title(f"{seg}\n({mode})", fontsize=8)
            if c == 0:
                ax.set_ylabel(f"{plane.replace('_', ' ')}\nROM (deg)", fontsize=8)
            if r == len(PLANES) - 1:
                ax.set_xlabel("weight (SD)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=6)
    fig.suptitle("Segmental ROM vs shape-mode weight (7.5 N.m; open marker: load not reached)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def _segment_key(s: pd.Series) -> pd.Series:
    """Sort key of mode ('lumbar' before 'unit') and segment names (cranial first: T before L before S)."""
    if s.name == "mode":
        return s
    from spinecohort.rom.submodel import COLUMN

    return s.map(lambda seg: COLUMN.index(seg.split("-")[0]))


def rom_sensitivity_figure(sens: pd.DataFrame, path: str | Path) -> Path:
    """Change of every compared ROM (columns; deg) with each calibrated parameter at the low and high end
    of its published range (rows), `spinecohort.rom.sensitivity.sensitivity` table, as an annotated heat map."""
    d = sens[sens["parameter"] != "baseline"].copy()
    d["row"] = d["parameter"] + " " + d["level"] + " (" + d["value"].map("{:g}".format) + ")"
    if "max_guide_moment_nmm" in d:  # a variant with a guided case: its values include a constrained one
        guided = d["max_guide_moment_nmm"] > 0
        d.loc[guided, "row"] += " [guided " + d.loc[guided, "max_guide_moment_nmm"].map("{:.0f}".format) + " N.mm]"
    d["col"] = d["segment"] + " " + d["motion"].str.replace("_", " ") + " (" + d["side"] + ")"
    order_cols = list(dict.fromkeys(d["col"]))
    # a comparison without value in every variant (a case short of the full load) stays as an empty column
    m = d.pivot_table(index="row", columns="col", values="change_deg", sort=False, dropna=False)
    m = m.reindex(index=list(dict.fromkeys(d["row"])), columns=order_cols)
    lim = max(float(np.nanmax(np.abs(m.to_numpy()))), 0.1)
    fig, ax = plt.subplots(figsize=(0.75 * m.shape[1] + 4, 0.32 * m.shape[0] + 2.5))
    im = ax.imshow(m.to_numpy(), cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
    for (i, j), v in np.ndenumerate(m.to_numpy()):
        if np.isfinite(v):
            colour = "white" if abs(v) > 0.6 * lim else "black"  # legible on the darkest cells
            ax.text(j, i, f"{v:+.1f}", ha="center", va="center", fontsize=6, color=colour)
        else:  # not compared: that case stopped short of the full moment (the table's min_load_fraction)
            ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor="0.85", hatch="///", edgecolor="0.6"))
            ax.text(j, i, "short", ha="center", va="center", fontsize=6, color="0.25")
    ax.set_xticks(range(m.shape[1]), m.columns, rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(m.shape[0]), m.index, fontsize=7)
    fig.colorbar(im, ax=ax, label="change of ROM from the calibrated model (deg)")
    ax.set_title(
        "ROM sensitivity: each parameter at the ends of its published range (functional units, 7.5 N.m;"
        " hatched: case short of the load, not compared)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
