"""numpy meshes as VTK data sets (pyvista objects, which are the VTK classes themselves).

One place builds them, so registration, morphing, repair, the figures, the platform, the benchmarks and the
tests hand the same arrays to VTK the same way: points (N, 3) in mm, cells as (M, k) node indices in VTK
order (triangles k = 3, quads k = 4, line segments k = 2, hexahedra k = 8 as VTK_HEXAHEDRON = C3D8).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv


def cell_array(cells: np.ndarray) -> np.ndarray:
    """VTK's flat cell array ``[k, i0 .. ik-1, k, ...]`` of (M, k) same-size cells."""
    cells = np.asarray(cells, dtype=np.int64)
    return np.hstack([np.full((len(cells), 1), cells.shape[1], dtype=np.int64), cells]).ravel()


def surface(points_mm: np.ndarray, faces: np.ndarray) -> pv.PolyData:
    """A polygon surface of same-size faces (triangles or quads)."""
    return pv.PolyData(np.asarray(points_mm, dtype=float), faces=cell_array(faces))


def polylines(points_mm: np.ndarray, segments: np.ndarray) -> pv.PolyData:
    """Line segments (M, 2), e.g. the ligaments."""
    return pv.PolyData(np.asarray(points_mm, dtype=float), lines=cell_array(segments))


def hexahedra(points_mm: np.ndarray, hexes: np.ndarray) -> pv.UnstructuredGrid:
    """An unstructured grid of hexahedra (VTK_HEXAHEDRON node order)."""
    return pv.UnstructuredGrid(
        {pv.CellType.HEXAHEDRON: np.asarray(hexes, dtype=np.int64)}, np.asarray(points_mm, dtype=float)
    )
