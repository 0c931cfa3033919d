"""The off-screen render of a hex model coloured by tissue, its surface parts muted and its ligaments
coloured by group (pyvista), with the colours the platform shares and the cameras of the figures."""

from __future__ import annotations

import matplotlib.cm
import matplotlib.colors
import matplotlib.lines
import numpy as np

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


def view_camera(plotter, view: str, focal: np.ndarray, parallel_scale: float) -> None:
    """Parallel projection; 'lateral' looks from the patient's right (+x, anterior on the right),
    'frontal' from anterior (+y, the patient's right on the left); z up."""
    direction = {"lateral": np.array([1.0, 0, 0]), "frontal": np.array([0, 1.0, 0])}[view]
    plotter.enable_parallel_projection()
    plotter.camera.focal_point = tuple(focal)
    plotter.camera.position = tuple(focal + 2000.0 * direction)
    plotter.camera.up = (0.0, 0.0, 1.0)
    plotter.camera.parallel_scale = parallel_scale
    plotter.camera.clipping_range = (1.0, 5000.0)


def framing(points: np.ndarray, view: str, size_px: tuple[int, int], margin: float = 1.04):
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
        focal, parallel_scale = framing(points, view, size_px)

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
    view_camera(pl, view, np.asarray(focal, float), float(parallel_scale))
    img = pl.screenshot(return_img=True)
    pl.close()
    return np.asarray(img)[..., :3]


def part_legend_handles(ligament_groups=None):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=c, edgecolor="#555555", label=label) for label, c in HEX_PART_STYLE.values()]
    handles.append(Patch(facecolor=SURFACE_STYLE[1], edgecolor="#555555", label=SURFACE_STYLE[0]))
    for g, (label, c) in LIGAMENT_STYLE.items():
        if ligament_groups is None or g in ligament_groups:
            handles.append(Line2D([0], [0], color=c, lw=3, label=label))
    return handles
