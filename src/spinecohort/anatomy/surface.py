"""Triangle-surface operations of the reference build: isotropic remeshing, checks, sphere fits.

All coordinates in millimetres.  Meshes are ``(vertices (N, 3), faces (F, 3))`` pairs at the package
boundary; pyvista/VTK objects stay inside the functions.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv


def to_polydata(vertices: np.ndarray, faces: np.ndarray) -> pv.PolyData:
    faces = np.asarray(faces, dtype=np.int64)
    return pv.PolyData(np.asarray(vertices, float), np.c_[np.full(len(faces), 3), faces].ravel())


def from_polydata(mesh: pv.PolyData) -> tuple[np.ndarray, np.ndarray]:
    mesh = mesh.triangulate()
    return np.asarray(mesh.points, float), np.asarray(mesh.faces).reshape(-1, 4)[:, 1:].astype(np.int64)


def remesh_isotropic(vertices: np.ndarray, faces: np.ndarray, edge_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Uniform remesh by Voronoi clustering (ACVD, Valette et al. 2008, package ``pyacvd``) to triangles of
    about ``edge_mm`` edge length: the cluster count is the surface area over twice the area of an
    equilateral triangle of that edge (an isotropic triangulation has two triangles per vertex)."""
    import pyacvd  # build-time dependency only (the ``reference`` extra)

    if not edge_mm > 0:
        raise ValueError(f"edge length must be positive, got {edge_mm} mm")
    mesh = to_polydata(vertices, faces).clean()
    n = int(round(mesh.area / (np.sqrt(3.0) / 4.0 * edge_mm**2) / 2.0))
    clus = pyacvd.Clustering(mesh)
    while clus.mesh.n_points < 6 * n:  # enough fine points per cluster for an even Voronoi partition
        clus.subdivide(2)
    clus.cluster(n)
    return from_polydata(clus.create_mesh().clean())


def edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(E,) length of every undirected edge, mm."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    return np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)


def _contacts(mesh_a: pv.PolyData, mesh_b: pv.PolyData):
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    f = vtk.vtkCollisionDetectionFilter()
    f.SetInputData(0, mesh_a)
    f.SetInputData(1, mesh_b)
    f.SetTransform(0, vtk.vtkTransform())
    f.SetTransform(1, vtk.vtkTransform())
    f.SetCollisionModeToAllContacts()
    f.SetBoxTolerance(0.0)
    f.SetCellTolerance(0.0)
    f.SetNumberOfCellsPerNode(2)
    f.Update()
    a = f.GetOutput(0).GetFieldData().GetArray("ContactCells")
    if a is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return vtk_to_numpy(a), vtk_to_numpy(f.GetOutput(1).GetFieldData().GetArray("ContactCells"))


def intersections_between(va: np.ndarray, fa: np.ndarray, vb: np.ndarray, fb: np.ndarray) -> int:
    """Number of intersecting triangle pairs between two surfaces (0: they do not interpenetrate or touch)."""
    return int(len(_contacts(to_polydata(va, fa), to_polydata(vb, fb))[0]))


def self_intersections(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Number of intersecting triangle pairs that share no vertex (0 for a surface without self-intersections;
    VTK's OBB-tree collision filter run on the mesh against itself)."""
    mesh = to_polydata(vertices, faces)
    a, b = _contacts(mesh, mesh)
    share = (faces[a][:, :, None] == faces[b][:, None, :]).any(axis=(1, 2))
    return int(np.sum(~share) // 2)  # every pair is reported in both orders


def check_surface(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Closedness, manifoldness, Euler genus, self-intersections and edge-length statistics of a surface."""
    mesh = to_polydata(vertices, faces)
    el = edge_lengths(vertices, faces)
    n_e = len(el)
    n_comp = int(mesh.connectivity().point_data["RegionId"].max() + 1) if mesh.n_points else 0
    chi = len(vertices) - n_e + len(faces)
    return {
        "vertices": int(len(vertices)),
        "triangles": int(len(faces)),
        "components": n_comp,
        "open_edges": int(mesh.n_open_edges),
        "manifold": bool(mesh.is_manifold),
        "genus_total": int(n_comp - chi // 2),
        "self_intersections": self_intersections(vertices, faces),
        "edge_mean_mm": float(el.mean()),
        "edge_sd_mm": float(el.std()),
        "edge_min_mm": float(el.min()),
        "edge_max_mm": float(el.max()),
    }


def sphere_fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares sphere through (N, 3) points: centre (3,) mm, radius mm."""
    a = np.c_[2.0 * points, np.ones(len(points))]
    b = np.sum(points**2, axis=1)
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    centre = sol[:3]
    return centre, float(np.sqrt(sol[3] + centre @ centre))
