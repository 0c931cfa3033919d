"""Builders of known geometry shared by the tests and the benchmarks (as numpy.testing is numpy's).

Structured hexahedral grids are the closed-form cases of the quality, repair, deck-writing and solver
checks: every element's shape, volume and Jacobian is known, so a test can state the number it expects.
"""

from __future__ import annotations

import numpy as np


def hex_grid_node_id(shape: tuple[int, int, int], x_fastest: bool = False):
    """Node id of grid node (i, j, k) for an (nx, ny, nz)-element grid, as :func:`hex_grid` numbers them."""
    nx, ny, nz = shape
    if x_fastest:
        return lambda i, j, k: (k * (ny + 1) + j) * (nx + 1) + i
    return lambda i, j, k: (i * (ny + 1) + j) * (nz + 1) + k


def hex_grid(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, x_fastest: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 3) and hexahedra (E, 8), 0-based, of the tensor grid of the node coordinates xs, ys, zs (mm).

    Corner order is VTK_HEXAHEDRON = C3D8 (the bottom face (i, j), (i+1, j), (i+1, j+1), (i, j+1) at k, then
    the same at k+1), so a grid with increasing coordinates has positive Jacobians everywhere.  Nodes and
    elements are numbered with k fastest (``x_fastest=False``) or with i fastest (``x_fastest=True``)."""
    xs, ys, zs = (np.asarray(a, dtype=float) for a in (xs, ys, zs))
    shape = (len(xs) - 1, len(ys) - 1, len(zs) - 1)
    nid = hex_grid_node_id(shape, x_fastest)
    if x_fastest:
        z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
        k, j, i = (t.ravel() for t in np.meshgrid(*(np.arange(n) for n in shape[::-1]), indexing="ij"))
    else:
        x, y, z = np.meshgrid(xs, ys, zs, indexing="ij")
        i, j, k = (t.ravel() for t in np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"))
    nodes = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    hexes = np.column_stack(
        [
            nid(i, j, k),
            nid(i + 1, j, k),
            nid(i + 1, j + 1, k),
            nid(i, j + 1, k),
            nid(i, j, k + 1),
            nid(i + 1, j, k + 1),
            nid(i + 1, j + 1, k + 1),
            nid(i, j + 1, k + 1),
        ]
    )
    return nodes, hexes


def unit_cube_grid(n: int, h: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """n^3 cubes of edge h (mm), k fastest: node (i, j, k) has id (i (n+1) + j)(n+1) + k."""
    edge = np.arange(n + 1) * h
    return hex_grid(edge, edge, edge)


def perturbed_cube_grid(n: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`unit_cube_grid` with every node jittered by U(+-0.22) and 30 nodes kicked by N(0, 1): a few
    dozen inverted elements among valid ones (the repair and quality kernels' hard case)."""
    X, H = unit_cube_grid(n)
    rng = np.random.default_rng(seed)
    X += rng.uniform(-0.22, 0.22, X.shape)
    X[rng.choice(len(X), 30, replace=False)] += rng.normal(0.0, 1.0, (30, 3))
    return X, H


def deformed_bone_case(bone: str = "L3", seed: int = 3, **kwargs):
    """A bone of the synthetic reference (coarse) and its :func:`deformed_copy`: ``(source, faces, truth,
    target, target_faces)`` in mm."""
    from spinecohort.cohort.register import synthetic_reference

    ref = synthetic_reference("coarse")
    src, faces = ref.points[ref.vertices_of(bone)], ref.faces_of(bone)
    return (src, faces, *deformed_copy(src, faces, seed, **kwargs))


def deformed_copy(
    src: np.ndarray, faces: np.ndarray, seed: int = 3, n_bumps: int = 5, width_mm: float = 12.0, angle_deg: float = 10.0
):
    """A deformed, moved, re-triangulated copy of a surface (mm), the truth known per point.

    The copy: ``n_bumps`` smooth Gaussian bumps (``width_mm`` wide, 2-5 mm each), a rotation of ``angle_deg``
    about an oblique axis through the centroid, a (5, -3, 2) mm shift; then subdivision + quadric decimation
    (no point of the copy is a source point) and shuffled points and triangles.  Returns ``(truth, target,
    target_faces)``; ``truth[i]`` is where ``src[i]`` went."""
    from scipy.spatial.transform import Rotation

    from spinecohort.cohort.user_folder import retriangulate

    rng = np.random.default_rng(seed)
    centre = src.mean(0)
    amps = rng.normal(size=(n_bumps, 3))
    amps *= (rng.uniform(2, 5, n_bumps) / np.linalg.norm(amps, axis=1))[:, None]
    centres = src[rng.choice(len(src), n_bumps, replace=False)]
    bumps = np.exp(-np.sum((src[:, None] - centres[None]) ** 2, axis=-1) / (2 * width_mm**2)) @ amps
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    rot = Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
    truth = (src + bumps - centre) @ rot.T + centre + [5.0, -3.0, 2.0]
    target, target_faces = retriangulate(truth, faces, rng)
    return truth, target, target_faces
