"""The potting of a vertebra whose endplate nodes carry a partial cartilage endplate's fibre ties.

A functional unit's loaded top vertebra is a *RIGID BODY and its bottom one fixed, as potted in vitro; the whole
model's loaded vertebra likewise.  With a partial CEP the annulus' rim fibres tie to those vertebrae's endplate
nodes, and ccx 2.20 cannot keep an embedded tie's host node in a rigid body or a fixed set
(`FEModel.embedded_hosts`).  A thin cortical plate holds each such node at a fixed distance from the potted
nodes, the same at every resolution of the template (docs/explanation/fe-model.md).  Units: mm.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from spinecohort.fe.abaqus import FEModel, Section


def potted_plate(
    fe: FEModel,
    quads: np.ndarray,
    carried: np.ndarray,
    plates: dict[str, tuple[np.ndarray, np.ndarray, float]],
    thickness_mm: float = 1.0,
) -> tuple[FEModel, dict[str, np.ndarray]]:
    """`fe` with a cortical-bone plate `thickness_mm` thick (block POTTING, set <vertebra>_POTTING) on every quad of a
    potted vertebra's node layer that holds a `carried` node, and the plates' far nodes per vertebra, which join the
    vertebra's rigid body or fixed set in place of the carried nodes.

    plates: vertebra -> (its node layer in O-grid order, its cranial unit vector (3,), +1 if its bone is cranial to
    the layer, -1 if caudal); quads: the O-grid's quads.  A fibre tie's host node cannot sit in a *RIGID BODY or a
    fixed set (`FEModel.embedded_hosts`); the plate holds it 1 mm from them at any mesh, where the bone's first hex
    layer alone would hold it by a quarter of the body's height at 4 body layers and an eighth at 8.  Inside a
    vertebra the plate overlaps that hex layer, as the endplate's cortex does."""
    n, first = len(fe.nodes), fe.n_elements
    nodes, conns, sets, new = [fe.nodes], [], {}, {}
    for v, (plate, cranial, side) in plates.items():
        q = quads[np.isin(plate, carried)[quads].any(axis=1)]
        used = np.unique(q)
        local = np.full(len(plate), -1, dtype=np.int64)
        local[used] = n + np.arange(len(used))
        nodes.append(fe.nodes[plate[used]] + side * thickness_mm * np.asarray(cranial, dtype=np.float64))
        # the template's hex order: the caudal face, then the cranial one
        faces = (local[q], plate[q]) if side < 0 else (plate[q], local[q])
        conns.append(np.concatenate(faces, axis=1))
        sets[f"{v}_POTTING"] = first + np.arange(len(q))
        new[v] = local[used]
        n, first = n + len(used), first + len(q)
    if not sum(len(c) for c in conns):
        return fe, {v: np.zeros(0, np.int64) for v in plates}
    fe = dataclasses.replace(
        fe,
        nodes=np.concatenate(nodes),
        element_blocks={**fe.element_blocks, "POTTING": ("C3D8", np.concatenate(conns))},
        element_sets={**fe.element_sets, **{k: s for k, s in sets.items() if len(s)}},
        sections=[*fe.sections, *(Section(elset=k, material="CORTICAL") for k, s in sets.items() if len(s))],
    )
    return fe, new
