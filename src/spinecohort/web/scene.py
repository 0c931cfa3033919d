"""The 3D scene of the platform: a hex model as one VTK polydata coloured by tissue, for vtk.js.

The server builds VTK objects but never renders them: trame-vtk's local view serialises the scene and
vtk.js draws it in the browser (no OpenGL on the server).  The topology of a model is the template's and
never changes, so the polydata is built once; a new model, or a slider move, only replaces its point
coordinates (one (n_nodes, 3) array), and the view sends the changed array.

Colours are the figures' (``figures.HEX_PART_STYLE``, ``SURFACE_STYLE``, ``LIGAMENT_STYLE``): the outer
faces of the hexes by tissue (cancellous core, cortical shell, NP, AF, CEP), the S3 surface parts
(posterior elements, sacrum, pelvis, femoral heads) muted, the ligaments by group.
"""

from __future__ import annotations

import matplotlib.colors
import numpy as np

from spinecohort.figures.render import (
    HEX_PART_STYLE,
    LIGAMENT_STYLE,
    SURFACE_STYLE,
    hex_boundary_faces,
    hex_tissue,
    ligament_group,
)


def _rgb255(colour: str) -> np.ndarray:
    return (255 * np.array(matplotlib.colors.to_rgb(colour))).round().astype(np.uint8)


def model_topology(template) -> dict:
    """Cells and per-cell colours of a hex model, in VTK's cell order (lines, then polygons).

    Returns lines (L, 2), quads (F, 4) the hexes' boundary faces, tris (T, 3) the surface parts, and rgb
    (L + F + T, 3) uint8."""
    quads, owner = hex_boundary_faces(template.hexes)
    tissue = hex_tissue(template)[owner]
    tissue_rgb = {t: _rgb255(c) for t, (_, c) in HEX_PART_STYLE.items()}
    lig_rgb = {g: _rgb255(c) for g, (_, c) in LIGAMENT_STYLE.items()}
    group = ligament_group(template)
    rgb = np.concatenate(
        [
            np.array([lig_rgb[g] for g in group], np.uint8).reshape(-1, 3),
            np.array([tissue_rgb[t] for t in tissue], np.uint8).reshape(-1, 3),
            np.repeat(_rgb255(SURFACE_STYLE[1])[None], len(template.tris), axis=0),
        ]
    )
    return {"lines": template.ligaments, "quads": quads, "tris": template.tris, "rgb": rgb}


def model_polydata(topology: dict, points: np.ndarray):
    """vtkPolyData of a model: ``points`` (n_nodes, 3) mm as float32, lines and polygons of ``topology``, cell
    colours in the uint8 array ``rgb`` (drawn as they are: the mapper's direct-scalar mode)."""
    from vtkmodules.util.numpy_support import numpy_to_vtk

    from spinecohort.mesh.vtk_mesh import polydata

    pd_ = polydata(
        np.ascontiguousarray(points, np.float32),
        polys=(topology["quads"], topology["tris"]),
        lines=(topology["lines"],),
    )
    colours = numpy_to_vtk(np.ascontiguousarray(topology["rgb"]), deep=True)
    colours.SetName("tissue_rgb")
    pd_.GetCellData().SetScalars(colours)
    return pd_


def set_points(polydata, points: np.ndarray) -> None:
    """Replace the coordinates (n_nodes, 3) mm of ``polydata`` in place (same node count)."""
    from vtkmodules.util.numpy_support import numpy_to_vtk

    pts = np.ascontiguousarray(points, np.float32)
    if pts.shape[0] != polydata.GetNumberOfPoints():
        raise ValueError(f"{pts.shape[0]} points for a polydata of {polydata.GetNumberOfPoints()}")
    polydata.GetPoints().SetData(numpy_to_vtk(pts, deep=True))
    polydata.GetPoints().Modified()
    polydata.Modified()


def orientation_marker(bounds) -> object:
    """An actor of three arrows with letters at the tips, R (right, +x), A (anterior, +y), S (superior, +z),
    beside the posterior-inferior corner of ``bounds`` (mm): it turns with the model, so the directions stay
    readable from any view.  Sized at 12 % of the model's height."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonTransforms import vtkTransform
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData
    from vtkmodules.vtkFiltersGeneral import vtkTransformFilter
    from vtkmodules.vtkFiltersSources import vtkArrowSource
    from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper
    from vtkmodules.vtkRenderingFreeType import vtkVectorText

    b = np.asarray(bounds, float)
    size = 0.12 * max(b[5] - b[4], 1.0)
    origin = np.array([(b[0] + b[1]) / 2, b[2] - 0.3 * size, b[4]])
    append = vtkAppendPolyData()
    # (letter, colour, rotation taking +x to the axis, text offset): the letters face +x (the right lateral view)
    for letter, rgb, rot in (
        ("R", (0.85, 0.1, 0.1), (0.0, 0.0, 0.0, 1.0)),
        ("A", (0.1, 0.6, 0.1), (90.0, 0.0, 0.0, 1.0)),
        ("S", (0.1, 0.2, 0.85), (-90.0, 0.0, 1.0, 0.0)),
    ):
        arrow, text = vtkArrowSource(), vtkVectorText()
        arrow.SetShaftResolution(12)
        arrow.SetTipResolution(12)
        text.SetText(letter)
        direction = vtkTransform()
        direction.Translate(*origin)
        direction.RotateWXYZ(*rot)
        direction.Scale(size, size, size)
        tip = np.array(direction.TransformPoint(1.15, 0.0, 0.0))
        place = vtkTransform()  # the letter in the y-z plane, facing +x, its lower left corner at the tip
        place.Translate(*tip)
        place.RotateWXYZ(90.0, 0.0, 1.0, 0.0)
        place.RotateWXYZ(90.0, 0.0, 0.0, 1.0)
        place.Scale(0.35 * size, 0.35 * size, 0.35 * size)
        for src, tf in ((arrow, direction), (text, place)):
            f = vtkTransformFilter()
            f.SetInputConnection(src.GetOutputPort())
            f.SetTransform(tf)
            f.Update()
            pd_ = f.GetOutput()
            colours = numpy_to_vtk(
                np.repeat((255 * np.array(rgb)).astype(np.uint8)[None], pd_.GetNumberOfCells(), axis=0), deep=True
            )
            colours.SetName("tissue_rgb")
            pd_.GetCellData().SetScalars(colours)
            append.AddInputData(pd_)
    append.Update()
    mapper = vtkPolyDataMapper()
    mapper.SetInputData(append.GetOutput())
    mapper.SetScalarModeToUseCellData()
    mapper.SetColorModeToDirectScalars()
    actor = vtkActor()
    actor.SetMapper(mapper)
    return actor


def legend_entries() -> list[dict]:
    """The tissue colours of the view for the page's legend: [{name, colour}] in drawing order."""
    out = [{"name": name, "colour": c} for name, c in HEX_PART_STYLE.values()]
    out.append({"name": SURFACE_STYLE[0], "colour": SURFACE_STYLE[1]})
    out += [{"name": name, "colour": c} for name, c in LIGAMENT_STYLE.values()]
    return out


class Scene:
    """A render window (never rendered on the server) with the selected model and a translucent overlay."""

    def __init__(
        self, template, points: np.ndarray, overlay_points: np.ndarray | None = None, topology: dict | None = None
    ):
        from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper, vtkRenderer, vtkRenderWindow

        self.topology = topology if topology is not None else model_topology(template)
        self.renderer = vtkRenderer()
        self.renderer.SetBackground(1.0, 1.0, 1.0)
        self.window = vtkRenderWindow()
        self.window.AddRenderer(self.renderer)
        self.polydata, self.actor = [], []
        for i, pts in enumerate((points, overlay_points if overlay_points is not None else points)):
            pd_ = model_polydata(self.topology, pts)
            mapper = vtkPolyDataMapper()
            mapper.SetInputData(pd_)
            mapper.SetScalarModeToUseCellData()
            mapper.SetColorModeToDirectScalars()
            mapper.ScalarVisibilityOn()
            actor = vtkActor()
            actor.SetMapper(mapper)
            if i == 1:  # the overlay: translucent grey, no tissue colours
                mapper.ScalarVisibilityOff()
                actor.GetProperty().SetColor(0.25, 0.45, 0.85)
                actor.GetProperty().SetOpacity(0.25)
                actor.SetVisibility(overlay_points is not None)
            self.renderer.AddActor(actor)
            self.polydata.append(pd_)
            self.actor.append(actor)
        self.marker = orientation_marker(self.polydata[0].GetBounds())
        self.renderer.AddActor(self.marker)
        self.reset_camera()

    def reset_camera(self, fill: float = 0.92) -> None:
        """A right lateral view (frame RAS: x right, y anterior, z up; anterior to the right of the screen,
        superior up) whose height the model fills to ``fill``: a spine is tall and thin, so fitting its
        bounding sphere (VTK's ResetCamera) would leave it a sliver.  The local view never renders on the
        server, so the camera must be placed before the first frame is serialised."""
        b = np.array(self.polydata[0].GetBounds())
        centre = (b[0::2] + b[1::2]) / 2
        height = max(b[5] - b[4], b[3] - b[2], 1.0)  # z extent; the y extent if a model lies on its side
        cam = self.renderer.GetActiveCamera()
        cam.SetViewAngle(30.0)
        dist = height / 2 / np.tan(np.radians(15.0)) / fill
        cam.SetFocalPoint(*centre)
        cam.SetPosition(centre[0] + dist + (b[1] - b[0]) / 2, centre[1], centre[2])
        cam.SetViewUp(0.0, 0.0, 1.0)
        self.renderer.ResetCameraClippingRange()

    def show(self, points: np.ndarray) -> None:
        set_points(self.polydata[0], points)

    def overlay(self, points: np.ndarray | None) -> None:
        if points is None:
            self.actor[1].SetVisibility(False)
        else:
            set_points(self.polydata[1], points)
            self.actor[1].SetVisibility(True)
