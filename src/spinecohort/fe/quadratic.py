"""Quadratic (20-node) hexes inside a linear hex mesh, kept conforming by midside-node ties.

Why (docs/explanation/fe-model.md): ccx 2.20's C3D8R discs do not keep moment equilibrium once the hexes are distorted
and the nucleus is nearly incompressible (the S1 plate of the T10-S1 model carries 87 % of 7.5 N.m), and a
fully integrated C3D8 nucleus locks.  C3D20R needs no hourglass control and does not lock, so the disc soft
tissue can be quadratic while bone and cartilage endplates stay C3D8.  Fully integrated C3D20 locks mildly but has
no spurious mode for the nucleus pressure to buckle: the whole-model load deck's nucleus
(`spinecohort.fe.pure_moment.fully_integrated_nucleus`).

Conformity: a C3D8 face is bilinear, so along each of its edges the displacement is linear.  A midside node
of a quadratic hex that lies on an edge of a linear neighbour must therefore move as the mean of that edge's
two corner nodes: ``u_m - u_a/2 - u_b/2 = 0`` per direction (``*EQUATION``, `FEModel.midside_ties`).  The
midside node is new, so it is free to be the dependent term.  Interior and free-surface midside nodes are
left free.

Node order of C3D20/C3D20R (Abaqus and ccx): the 8 corners as in C3D8, then the midside nodes of edges
1-2, 2-3, 3-4, 4-1, 5-6, 6-7, 7-8, 8-5, 1-5, 2-6, 3-7, 4-8.  Units: mm.
"""

from __future__ import annotations

import numpy as np

from spinecohort.fe.abaqus import SOLID_TYPES

#: the 20-node hexes: C3D20 (27 integration points) and C3D20R (8, reduced)
QUADRATIC_TYPES = frozenset({"C3D20", "C3D20R"})
#: corner pairs (0-based) of the 12 edges of a hex, in the order of C3D20's midside nodes 9..20
HEX20_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]], dtype=np.int64
)


def _edge_keys(hexes8: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """(E*12, 2) sorted corner pairs of every edge of `hexes8` and their scalar keys a*n + b (a < b)."""
    pairs = np.sort(np.asarray(hexes8, dtype=np.int64)[:, HEX20_EDGES].reshape(-1, 2), axis=1)
    return pairs, pairs[:, 0] * np.int64(n_nodes) + pairs[:, 1]


def quadratic_hexes(
    points_mm: np.ndarray, hexes8: np.ndarray, linear_neighbours: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turn the 8-node hexes `hexes8` (E, 8) (0-based into `points_mm` (N, 3) mm) into 20-node hexes.

    Returns ``(midside_mm, hexes20, ties)``: the coordinates of the new midside nodes (M, 3), one per
    distinct edge, at the edge's midpoint (to be appended after `points_mm`, so their indices are
    N .. N+M-1); the (E, 20) connectivity in C3D20 order; and the (K, 3) ties ``[midside, a, b]`` of every
    midside node whose edge (a, b) is also an edge of a hex in `linear_neighbours` (E2, 8), which keeps the
    two meshes conforming (module docstring)."""
    points_mm = np.asarray(points_mm, dtype=np.float64)
    n = len(points_mm)
    hexes8 = np.asarray(hexes8, dtype=np.int64)
    pairs, keys = _edge_keys(hexes8, n)
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    edge_nodes = pairs[first]  # (M, 2)
    midside = 0.5 * (points_mm[edge_nodes[:, 0]] + points_mm[edge_nodes[:, 1]])
    hexes20 = np.concatenate([hexes8, n + inverse.reshape(len(hexes8), 12)], axis=1)
    ties = np.zeros((0, 3), dtype=np.int64)
    if linear_neighbours is not None and len(linear_neighbours):
        _, other = _edge_keys(linear_neighbours, n)
        shared = np.isin(uniq, other)
        ties = np.column_stack([n + np.flatnonzero(shared), edge_nodes[shared]])
    return midside, hexes20, ties


def quadratic_blocks(
    points_mm: np.ndarray, blocks: dict[str, tuple[str, np.ndarray]]
) -> tuple[np.ndarray, dict[str, tuple[str, np.ndarray]], np.ndarray | None]:
    """Give every hex block of `blocks` ({name: (type, (E, 8) 0-based)}) of a 20-node type (`QUADRATIC_TYPES`)
    its midside nodes (shared between those blocks), tied to the 8-node hexes of the other blocks.  Returns
    the points with the midside nodes appended, the blocks with (E, 20) connectivity and the (K, 3) ties
    (none without a quadratic block)."""
    quad = [name for name, (etype, _) in blocks.items() if etype in QUADRATIC_TYPES]
    if not quad:
        return points_mm, blocks, np.zeros((0, 3), dtype=np.int64)
    linear = [conn for etype, conn in blocks.values() if etype not in QUADRATIC_TYPES and etype in SOLID_TYPES]
    conn8 = np.concatenate([blocks[name][1] for name in quad])
    midside, hex20, ties = quadratic_hexes(
        points_mm, conn8, np.concatenate(linear) if linear else np.zeros((0, 8), np.int64)
    )
    out = dict(blocks)
    start = 0
    for name in quad:
        n = len(blocks[name][1])
        out[name] = (blocks[name][0], hex20[start : start + n])
        start += n
    return np.concatenate([np.asarray(points_mm, dtype=np.float64), midside]), out, ties


def ties_on(ties: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """(K,) bool: the tie's edge lies on `nodes` (a rigid body, the fixed nodes).  Such a midside node moves with
    that set exactly (the midpoint of a rigidly moving or fixed edge), so it joins the set instead of hanging an
    *EQUATION on nodes the set already constrains."""
    return np.isin(np.asarray(ties)[:, 1:], nodes).all(axis=1)
