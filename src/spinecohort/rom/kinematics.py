"""Segmental rotations from the solver's displacements: a best-fit rotation per vertebra from its two endplate
node layers (Kabsch on reference vs displaced positions, `spinecohort.ssm.procrustes.kabsch`), then the
relative rotation of each upper vertebra with respect to the one below, as a rotation vector projected on the
segment's anatomical axes (lateral, anterior, cranial from the endplate planes; frame RAS: x right,
y anterior, z up).  Degrees."""

from __future__ import annotations

import numpy as np

from spinecohort.fe.facets import mean_frame
from spinecohort.rom.submodel import RomModel
from spinecohort.ssm.procrustes import kabsch


def rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (B, 3) in radians of rotation matrices (B, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_rotvec()


def segment_rotations_deg(model: RomModel, disp_of_node: dict[int, np.ndarray]) -> dict[tuple[str, str], np.ndarray]:
    """Relative rotation of every segment's upper vertebra w.r.t. its lower one, as (lateral, anterior,
    cranial) components in degrees of the segment's frame (mean of both vertebrae's frames).

    disp_of_node: 0-based submodel node -> (3,) displacement mm (must cover every endplate node)."""
    names = model.vertebrae
    k = max(len(model.endplate_nodes[v]) for v in names)
    ref = np.empty((len(names), k, 3))
    disp = np.empty_like(ref)
    for i, v in enumerate(names):
        ids = model.endplate_nodes[v]
        # pad the S1 plate's single layer by repetition: Kabsch is invariant to duplicated points' weights
        # only up to weighting, and S1 is fixed (zero rotation) anyway
        idx = np.resize(ids, k)
        ref[i] = model.fe.nodes[idx]
        disp[i] = np.array([disp_of_node[j] for j in idx])
    rot, _, _ = kabsch(ref, ref + disp)
    out = {}
    for i, (up, lo) in enumerate(model.segments()):
        rel = rot[i + 1].T @ rot[i]
        frame = mean_frame(model.frames[up], model.frames[lo])
        out[(up, lo)] = np.degrees(rotvec(rel[None])[0] @ frame)
    return out
