"""The moment the fixation of a ROM model carries, from the reaction forces of its fixed nodes.

A ROM deck (`spinecohort.rom.deck`) fixes U1-U3 of the nodes of set FIXED and prints their reaction forces
(``*NODE PRINT, NSET=FIXED`` with ``RF``).  Fixed nodes do not move, so the reaction moment about any point p
is sum_i (x_i - p) x RF_i with the undeformed coordinates, and global equilibrium says the load on the top
(a pure moment: zero net force) is minus that reaction.  This is the physical moment the spine carries, to
be compared with the ``*CLOAD`` on the top's ROT NODE (a generalised force conjugate to its rotation vector).
Units: mm, N, N.mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spinecohort.fe.calculix import NodePrint


@dataclass(frozen=True)
class Reaction:
    """Resultant of the fixed nodes' reaction forces at one step time: force (3,) N, moment (3,) N.mm about
    `point` (3,) mm (the fixed nodes' centroid unless given), number of nodes."""

    time: float
    force_n: np.ndarray
    moment_nmm: np.ndarray
    point_mm: np.ndarray
    n_nodes: int

    def carried_nmm(self) -> np.ndarray:
        """The moment the spine carries (the load that balances the reaction): minus the reaction moment."""
        return -self.moment_nmm


def reaction_resultant(coords_mm: dict[int, np.ndarray], block: NodePrint, point_mm=None) -> Reaction:
    """Net force and moment (about `point_mm`, default the nodes' centroid) of one RF block of the `.dat`
    (node ids as in the deck; `coords_mm`: node id -> undeformed coordinates)."""
    if block.values.shape[1] != 3:
        raise ValueError(f"block {block.quantity!r} of set {block.node_set} has {block.values.shape[1]} columns, not 3")
    x = np.array([coords_mm[int(i)] for i in block.node_ids], dtype=np.float64)
    rf = np.asarray(block.values, dtype=np.float64)
    p = x.mean(0) if point_mm is None else np.asarray(point_mm, dtype=np.float64)
    return Reaction(block.time, rf.sum(0), np.cross(x - p, rf).sum(0), p, len(rf))


def reactions(coords_mm: dict[int, np.ndarray], prints: list[NodePrint], node_set: str = "FIXED", point_mm=None):
    """`Reaction` of every RF block of `node_set` (one per printed increment), in step-time order."""
    blocks = [b for b in prints if b.node_set.upper() == node_set.upper() and b.quantity.lower().startswith("forces")]
    return [reaction_resultant(coords_mm, b, point_mm) for b in blocks]


def moving_resultants(coords_mm: dict[int, np.ndarray], prints: list[NodePrint], node_set: str) -> list[Reaction]:
    """`Reaction` of every RF block of a set whose nodes move, each with its lever arms to the nodes' positions at
    that increment (undeformed `coords_mm` plus the set's U block of the same step time; an RF block without one
    is skipped): the resultant of the forces the set's nodes pass to the rest of the model."""
    ours = [b for b in prints if b.node_set.upper() == node_set.upper()]
    u = {b.time: b for b in ours if b.quantity.lower().startswith("displacements")}
    out = []
    for b in ours:
        if b.quantity.lower().startswith("forces") and b.time in u:
            moved = {int(i): coords_mm[int(i)] + d for i, d in zip(u[b.time].node_ids, u[b.time].values)}
            out.append(reaction_resultant(moved, b))
    return out


def moment_on_top(deck_text: str, prints: list[NodePrint], top: str = "T1") -> list[Reaction]:
    """Per printed increment of a whole-model load deck (`spinecohort.fe.pure_moment.model_load_text`), the
    resultant of the forces the rigid top's nodes (set ``RB_<top>``) pass to the spine: its moment (N.mm) is the
    load plus, on a guided top, the moment that holds it on the load's axis; its force ~0 (a pure moment)."""
    return moving_resultants(deck_nodes_and_loads(deck_text)[0], prints, f"RB_{top}")


def deck_nodes_and_loads(text: str) -> tuple[dict[int, np.ndarray], list[tuple[int, int, float]]]:
    """Node coordinates (id -> (3,) mm, every *NODE block: the mesh and the rigid bodies' nodes) and the
    ``*CLOAD`` lines (node, dof, value) of a ccx deck as `spinecohort.rom.deck` writes it."""
    nodes: dict[int, np.ndarray] = {}
    cloads: list[tuple[int, int, float]] = []
    mode = None
    for line in text.splitlines():
        s = line.strip()
        if not s or s.startswith("**"):
            continue
        if s.startswith("*"):
            mode = {"NODE": "node", "CLOAD": "cload"}.get(s[1:].split(",")[0].strip().upper())
            continue
        fields = [f for f in s.split(",") if f.strip()]
        if mode == "node":
            nodes[int(fields[0])] = np.array([float(f) for f in fields[1:4]])
        elif mode == "cload":
            cloads.append((int(fields[0]), int(fields[1]), float(fields[2])))
    return nodes, cloads


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotation_vector_tangent(theta: np.ndarray) -> np.ndarray:
    """T(theta) (3, 3) of a rotation vector theta (rad): the spatial angular velocity is T(theta) dtheta/dt,
    T = I + (1 - cos t) / t^2 W + (t - sin t) / t^3 W^2 (t = |theta|, W = skew(theta))."""
    th = np.asarray(theta, dtype=np.float64)
    t = float(np.linalg.norm(th))
    w = _skew(th)
    if t < 1e-6:
        return np.eye(3) + 0.5 * w + w @ w / 6.0
    return np.eye(3) + (1.0 - np.cos(t)) / t**2 * w + (t - np.sin(t)) / t**3 * w @ w


def physical_moment(generalised_nmm: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The moment (N.mm) a ``*CLOAD`` `generalised_nmm` on a ccx 2.20 ROT NODE exerts once the ROT NODE has
    turned by the rotation vector `theta` (rad): ccx's load is the generalised force conjugate to the rotation
    vector, Q = T(theta)^T M, so M = T(theta)^-T Q (measured to 0.01 % on an elastic column turned 20 deg about
    an oblique axis, tests/test_rom.py).  About a fixed axis (theta parallel to Q) M = Q."""
    return np.linalg.solve(rotation_vector_tangent(theta).T, np.asarray(generalised_nmm, dtype=np.float64))


def generalised_load(moment_nmm: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The ROT NODE ``*CLOAD`` that exerts the physical moment `moment_nmm` at rotation vector `theta`:
    T(theta)^T M (the inverse of `physical_moment`)."""
    return rotation_vector_tangent(theta).T @ np.asarray(moment_nmm, dtype=np.float64)
