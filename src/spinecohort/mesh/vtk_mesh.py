"""numpy meshes as VTK data sets (pyvista objects, which are the VTK classes themselves).

One place builds them, so registration, morphing, repair, the figures, the platform, the benchmarks and the
tests hand the same arrays to VTK the same way: points (N, 3) in mm, cells as (M, k) node indices in VTK
order (triangles k = 3, quads k = 4, line segments k = 2, hexahedra k = 8 as VTK_HEXAHEDRON = C3D8).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv


def cell_array(*blocks: np.ndarray) -> np.ndarray:
    """VTK's flat cell array ``[k, i0 .. ik-1, k, ...]`` of blocks of (M, k) cells (k may differ between blocks)."""
    parts = [
        np.hstack([np.full((len(b), 1), b.shape[1], dtype=np.int64), b]).ravel()
        for b in (np.asarray(c, dtype=np.int64) for c in blocks)
        if len(b)
    ]
    return np.concatenate(parts) if parts else np.empty(0, np.int64)


def _points(points_mm: np.ndarray) -> np.ndarray:
    p = np.asarray(points_mm)
    return p if np.issubdtype(p.dtype, np.floating) else p.astype(float)  # float32 stays float32 (half the bytes)


def polydata(points_mm: np.ndarray, polys: tuple = (), lines: tuple = ()) -> pv.PolyData:
    """Polygons (blocks of triangles and/or quads) and line segments on one point set; cell data follow
    VTK's order: every line first, then every polygon, block by block."""
    faces, segs = cell_array(*polys), cell_array(*lines)
    return pv.PolyData(_points(points_mm), faces=faces if len(faces) else None, lines=segs if len(segs) else None)


def surface(points_mm: np.ndarray, faces: np.ndarray) -> pv.PolyData:
    """A polygon surface of same-size faces (triangles or quads)."""
    return polydata(points_mm, polys=(faces,))


def polylines(points_mm: np.ndarray, segments: np.ndarray) -> pv.PolyData:
    """Line segments (M, 2), e.g. the ligaments."""
    return polydata(points_mm, lines=(segments,))


def hexahedra(points_mm: np.ndarray, hexes: np.ndarray) -> pv.UnstructuredGrid:
    """An unstructured grid of hexahedra (VTK_HEXAHEDRON node order)."""
    return pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: np.asarray(hexes, dtype=np.int64)}, _points(points_mm))
