"""The 8-node hexahedron every quality metric is defined on: node order, edges, faces, the trilinear shape
functions at the points the metrics sample, and the input checks.

Node order is VTK_HEXAHEDRON = Verdict = Abaqus/CalculiX C3D8 = meshio ``hexahedron``: nodes 0-3 form one face,
counter-clockwise seen from the opposite face 4-7, node 4+i above node i.  A positively oriented element has
positive Jacobians.  Lengths in mm, Jacobian determinants in mm^3 (w.r.t. parametric coordinates in [0, 1]^3).

The numba kernels (`spinecohort.mesh.quality.kernels`) compile these tables in as constants, and numba's cache
does not notice a change made here: after editing a table, delete the ``__pycache__`` of this package.
"""

from __future__ import annotations

import numpy as np

VERDICT_DBL_MAX = 1.0e30
VERDICT_DBL_MIN = 1.0e-30

# Corner i of a VTK hex and its three edge neighbours (a, b, c); det[Pa-Pi, Pb-Pi, Pc-Pi] > 0 when valid.
CORNER_NEIGHBOURS = np.array(
    [[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]], dtype=np.int64
)
HEX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]],
    dtype=np.int64,
)
# Quad faces with outward normals by the right-hand rule (same as VTK's hex faces).
HEX_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]], dtype=np.int64
)
# Parametric corner positions (u, v, w) in [0, 1]^3 of the VTK node order.
HEX_CORNER_UVW = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64
)
CHUNK = 8192


def check_mesh(points: np.ndarray, hexes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points float64, hexes int64) after checking shapes, index range and finiteness (ValueError naming the
    problem)."""
    points = np.asarray(points, dtype=np.float64)
    hexes = np.asarray(hexes)
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (n_nodes, 3) or (B, n_nodes, 3), got {points.shape}")
    if hexes.ndim != 2 or hexes.shape[1] != 8:
        raise ValueError(f"hexes must have shape (E, 8) (C3D8 connectivity), got {hexes.shape}")
    if not np.issubdtype(hexes.dtype, np.integer):
        raise ValueError(f"hexes must be integer node indices, got dtype {hexes.dtype}")
    if hexes.size and (hexes.min() < 0 or hexes.max() >= points.shape[-2]):
        raise ValueError(
            f"hexes reference node {hexes.max() if hexes.max() >= points.shape[-2] else hexes.min()} "
            f"outside 0..{points.shape[-2] - 1}"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError("points contain NaN or inf")
    return points, hexes.astype(np.int64, copy=False)


def chunked(func, points: np.ndarray, hexes: np.ndarray, n_out: int = 1):
    """Apply ``func(P)`` with P (..., e, 8, 3) to element chunks and concatenate along the element axis."""
    points, hexes = check_mesh(points, hexes)
    outs = [[] for _ in range(n_out)]
    for start in range(0, max(len(hexes), 1), CHUNK):
        res = func(points[..., hexes[start : start + CHUNK], :])
        res = (res,) if n_out == 1 else res
        for o, r in zip(outs, res):
            o.append(r)
    cat = tuple(np.concatenate(o, axis=-1) for o in outs)
    return cat[0] if n_out == 1 else cat


def det3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """det[a, b, c] = a . (b x c) for vectors in the last axis."""
    return (
        a[..., 0] * (b[..., 1] * c[..., 2] - b[..., 2] * c[..., 1])
        + a[..., 1] * (b[..., 2] * c[..., 0] - b[..., 0] * c[..., 2])
        + a[..., 2] * (b[..., 0] * c[..., 1] - b[..., 1] * c[..., 0])
    )


#: the 2-point Gauss abscissae on [0, 1]; the 2x2x2 rule's points are their products
GAUSS_1D = 0.5 + np.array([-0.5, 0.5]) / np.sqrt(3.0)
_GAUSS_UVW = np.array([[u, v, w] for w in GAUSS_1D for v in GAUSS_1D for u in GAUSS_1D])
_HALF_UVW = np.array([[u, v, w] for u in (0.0, 0.5, 1.0) for v in (0.0, 0.5, 1.0) for w in (0.0, 0.5, 1.0)])


def _shape_derivatives(uvw: np.ndarray) -> np.ndarray:
    """dN_n/d(u, v, w) of the trilinear hex at parametric points uvw (Q, 3) in [0, 1]^3 -> (Q, 8, 3)."""
    c = HEX_CORNER_UVW[None]  # (1, 8, 3)
    x = uvw[:, None, :]  # (Q, 1, 3)
    one_d = np.where(c == 1.0, x, 1.0 - x)  # 1-D factor per axis
    d_one_d = np.where(c == 1.0, 1.0, -1.0)
    dN = np.empty((len(uvw), 8, 3))
    dN[..., 0] = d_one_d[..., 0] * one_d[..., 1] * one_d[..., 2]
    dN[..., 1] = one_d[..., 0] * d_one_d[..., 1] * one_d[..., 2]
    dN[..., 2] = one_d[..., 0] * one_d[..., 1] * d_one_d[..., 2]
    return dN


def _shape_functions(uvw: np.ndarray) -> np.ndarray:
    c = HEX_CORNER_UVW[None]
    x = uvw[:, None, :]
    return np.where(c == 1.0, x, 1.0 - x).prod(-1)  # (Q, 8)


#: shape-function derivatives (Q, 8, 3) at the 2x2x2 Gauss points, at the 27 points of {0, 1/2, 1}^3 (where det J
#: gives its Bernstein coefficients) and at the centre; shape functions (27, 8) at {0, 1/2, 1}^3 (subdivision)
DN_GAUSS = _shape_derivatives(_GAUSS_UVW)
DN_HALF = _shape_derivatives(_HALF_UVW)
DN_CENTRE = _shape_derivatives(np.array([[0.5, 0.5, 0.5]]))[0]
N_HALF = _shape_functions(_HALF_UVW)


def detj_at(P: np.ndarray, dN: np.ndarray) -> np.ndarray:
    """det J (w.r.t. u, v, w in [0, 1]) at the parametric points of dN (Q, 8, 3) -> (..., Q)."""
    J = np.einsum("qnd,...nx->...qdx", dN, P)  # rows: dX/du, dX/dv, dX/dw
    return det3(J[..., 0, :], J[..., 1, :], J[..., 2, :])


#: Lagrange values at u = 0, 1/2, 1 -> Bernstein coefficients of a quadratic (per parametric direction)
LAGRANGE_TO_BERNSTEIN = np.array([[1.0, 0.0, 0.0], [-0.5, 2.0, -0.5], [0.0, 0.0, 1.0]])
