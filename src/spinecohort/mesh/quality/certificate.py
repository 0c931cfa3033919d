"""Exact validity of trilinear hexahedra: the Bernstein certificate.

det J of a trilinear hex is tri-quadratic, so its 27 Bernstein coefficients bound it from below; subdividing at
1/2 resolves undecided elements (Johnen-Remacle-Geuzaine).  Written here because no Python library provides it;
subdivision re-evaluates the trilinear map on the child box, which equals de Casteljau splitting of the
coefficients up to a positive factor.  The first pass over all elements is the numba kernel
``bernstein_bounds_mesh_nb`` (`spinecohort.mesh.quality.kernels`); only the undecided few are subdivided here.
"""

from __future__ import annotations

import numpy as np

from spinecohort.mesh.quality.element import (
    DN_HALF,
    HEX_CORNER_UVW,
    LAGRANGE_TO_BERNSTEIN,
    N_HALF,
    check_mesh,
    detj_at,
)
from spinecohort.mesh.quality.kernels import bernstein_bounds_mesh_nb, bernstein_bounds_nb


def _bernstein_coefficients_P(P: np.ndarray) -> np.ndarray:
    """27 Bernstein coefficients of det J on [0,1]^3 -> (..., 3, 3, 3) indexed (u, v, w)."""
    f = detj_at(P, DN_HALF).reshape(*P.shape[:-2], 3, 3, 3)
    T = LAGRANGE_TO_BERNSTEIN
    return np.einsum("ai,bj,ck,...ijk->...abc", T, T, T, f)


def bernstein_coefficients(points: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Bernstein coefficients of det J (mm^3, parametric box [0,1]^3) -> (..., E, 3, 3, 3).

    Their minimum is a lower bound of det J over the element; the 8 corner coefficients are the corner
    Jacobians alpha_i.
    """
    points, hexes = check_mesh(points, hexes)
    return _bernstein_coefficients_P(points[..., hexes, :])


def _children(P: np.ndarray) -> np.ndarray:
    """Split hexes P (M, 8, 3) at parametric 1/2 -> (8M, 8, 3); det J of a child is det J / 8 > 0 iff parent's."""
    grid = np.einsum("qn,mnx->mqx", N_HALF, P).reshape(len(P), 3, 3, 3, 3)  # (M, u, v, w, xyz)
    corner = HEX_CORNER_UVW.astype(np.int64)
    kids = []
    for cu in (0, 1):
        for cv in (0, 1):
            for cw in (0, 1):
                kids.append(grid[:, cu + corner[:, 0], cv + corner[:, 1], cw + corner[:, 2], :])
    return np.stack(kids, axis=1).reshape(-1, 8, 3)


def _decide(min_coef: np.ndarray, min_corner: np.ndarray) -> np.ndarray:
    """+1 if every Bernstein coefficient > 0, -1 if a corner det J <= 0, 0 undecided."""
    result = np.zeros(len(min_coef), dtype=np.int8)
    result[min_coef > 0] = 1
    result[min_corner <= 0] = -1
    return result


def _subdivide_undecided(P: np.ndarray, max_depth: int) -> np.ndarray:
    """Resolve undecided hexes P (M, 8, 3) by halving: +1 valid, -1 invalid or still undecided at max_depth."""
    P = P - P.mean(axis=1, keepdims=True)
    P = P / np.abs(P).max(axis=(1, 2), keepdims=True).clip(1e-300)  # sign is scale-free; keep dets O(1)
    result = np.zeros(len(P), dtype=np.int8)
    owner = np.arange(len(P))
    boxes = P
    for _ in range(max_depth):
        if len(owner) == 0:
            break
        boxes = _children(boxes)
        owner = np.repeat(owner, 8)
        c = _bernstein_coefficients_P(boxes).reshape(len(boxes), 27)
        corner_min = c[:, [0, 2, 6, 8, 18, 20, 24, 26]].min(-1)
        result[np.unique(owner[corner_min <= 0])] = -1
        open_box = (c.min(-1) <= 0) & (result[owner] == 0)
        # an element is certified once none of its boxes is open
        still_open = np.unique(owner[open_box])
        result[np.setdiff1d(np.unique(owner[result[owner] == 0]), still_open)] = 1
        boxes, owner = boxes[open_box], owner[open_box]
    result[result == 0] = -1  # still undecided: not certified
    return result


def _certify_P(P: np.ndarray, max_depth: int) -> np.ndarray:
    """+1 valid / -1 invalid for gathered hexes P (M, 8, 3)."""
    result = _decide(*bernstein_bounds_nb(np.ascontiguousarray(P, dtype=np.float64)))
    undecided = np.flatnonzero(result == 0)
    result[undecided] = _subdivide_undecided(P[undecided], max_depth)
    return result


def certify_valid(points: np.ndarray, hexes: np.ndarray, max_depth: int = 6) -> np.ndarray:
    """Exact validity of each trilinear hex: +1 if det J > 0 everywhere inside, -1 otherwise -> (..., E) int8.

    Elements still undecided after ``max_depth`` halvings (det J touching 0 within 2**-max_depth of the
    parametric box) are reported -1, i.e. not certified. Typically < 1 % of elements need subdividing.
    """
    points, hexes = check_mesh(points, hexes)
    batch = points.reshape(-1, *points.shape[-2:])
    result = np.empty((len(batch), len(hexes)), dtype=np.int8)
    for b, X in enumerate(batch):  # one sample at a time: never gathers B x E x 8 x 3
        result[b] = _decide(*bernstein_bounds_mesh_nb(np.ascontiguousarray(X), hexes))
        undecided = np.flatnonzero(result[b] == 0)
        result[b, undecided] = _subdivide_undecided(X[hexes[undecided]], max_depth)
    return result.reshape(points.shape[:-2] + (len(hexes),))
