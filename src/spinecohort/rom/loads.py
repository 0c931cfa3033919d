"""What a ROM load case does inside the spine besides turning it: the nucleus pressure of every disc and the force
of every facet-joint contact strut, read from the ccx run's own ``.dat``.

* **Intradiscal pressure** (IDP): the hydrostatic pressure p = -tr(sigma) / 3 of the nucleus (element sets
  ``D_<upper><lower>_NP``), averaged over each element's integration points and weighted by element volume
  (``*EL PRINT`` of S and EVOL: ccx prints Cauchy stresses and the current volume).  The per-element mean
  weights each point as the parent element's rule does: C3D20's 27 points (3-point Gauss-Legendre in each
  direction, the first fastest) by the product of 5/9, 8/9, 5/9; the 8 points of C3D8 or C3D20R equally.
* **Facet force**: ccx 2.20 prints no force of a SPRINGA element (``*EL PRINT`` S and E print empty blocks for
  it, measured), so the force of each contact strut comes from its two nodes' printed displacements through the
  strut's own force-elongation table (the deck's ``*SPRING, NONLINEAR`` table: ccx interpolates it linearly and
  holds its end values beyond it, as `numpy.interp` does); compression positive, N.  Checked against ccx's own
  reaction at a strut's fixed node in tests/test_rom_loads.py.  Struts are summed by joint from their element-set
  names, ``FACET_<upper><lower>_<L|R>`` (one strut a joint) or ``FACET_<upper><lower>_<L|R>_<k>`` (several);
  ``FACET_TIP_...`` are the extension stops (the inferior articular process tip on the lamina below).

Units: mm, N, MPa.
"""

from __future__ import annotations

import re

import numpy as np
import pandas as pd

from spinecohort.fe.abaqus import FEModel
from spinecohort.fe.writers import format_id_list

#: the nucleus of a disc: D_L4L5_NP -> (L4, L5)
NUCLEUS_SET = re.compile(r"^D_([TL]\d{1,2})([TL]\d{1,2}|S1)_NP$")
#: a facet contact strut: FACET_L4L5_R, FACET_L4L5_R3 (the joint's third strut, `spinecohort.fe.facets`),
#: FACET_L4L5_R_3, FACET_TIP_L4L5_L -> (TIP_, L4, L5, R, 3)
FACET_SET = re.compile(r"^FACET_(TIP_)?([TL]\d{1,2})([TL]\d{1,2}|S1)_([LR])(?:_?(\w+))?$")
#: the node set of every facet strut's end nodes in a ROM deck (their displacements give the strut forces)
FACET_NODES = "FACETNODES"


def nucleus_sets(element_sets: dict) -> dict[str, str]:
    """Element-set name -> disc level ('L4-L5') of every nucleus set of a model."""
    out = {}
    for name in element_sets:
        m = NUCLEUS_SET.match(name)
        if m:
            out[name] = f"{m[1]}-{m[2]}"
    return out


def facet_struts(fe: FEModel) -> pd.DataFrame:
    """One row per facet contact strut of a model: element set, joint level ('L4-L5'), side (L/R), kind ('joint'
    contact or 'tip' extension stop), its two 0-based nodes and its force-elongation table (a tuple of (force N,
    elongation mm) pairs).  Empty when the model has no facet contact."""
    offsets = fe.block_offsets()
    conn = {}  # element index -> (node 1, node 2) of the SPRINGA blocks
    for name, (etype, c) in fe.element_blocks.items():
        if etype == "SPRINGA":
            conn.update({offsets[name] + i: tuple(map(int, c[i, :2])) for i in range(len(c))})
    tables = {s.elset: s.spring_force_elongation for s in fe.sections if s.spring_force_elongation}
    rows = []
    for name, idx in fe.element_sets.items():
        m = FACET_SET.match(name)
        if not m or name not in tables:
            continue
        for e in np.asarray(idx).ravel():
            n1, n2 = conn[int(e)]
            rows.append((name, f"{m[2]}-{m[3]}", m[4], "tip" if m[1] else "joint", n1, n2, tables[name]))
    cols = ["elset", "joint", "side", "kind", "node1", "node2", "table"]
    return pd.DataFrame(rows, columns=cols)


def load_print_text(fe: FEModel) -> tuple[str, str]:
    """(model data, step output) a ROM deck needs for `nucleus_pressure` and `facet_forces`: the node set of the
    facet struts' nodes, and *EL PRINT of S and EVOL per nucleus set, *NODE PRINT of U of those nodes."""
    struts = facet_struts(fe)
    data, step = "", ""
    if len(struts):
        nodes = np.unique(struts[["node1", "node2"]].to_numpy())
        data = f"*NSET, NSET={FACET_NODES}\n" + format_id_list(nodes + 1)
        step = f"*NODE PRINT, NSET={FACET_NODES}, GLOBAL=YES\nU\n"
    step += "".join(f"*EL PRINT, ELSET={name}\nS, EVOL\n" for name in sorted(nucleus_sets(fe.element_sets)))
    return data, step


def with_load_prints(deck: str, fe: FEModel) -> str:
    """A ROM deck (model data, one *STEP ... *END STEP) with `load_print_text`'s sets before its step and its
    prints at the end of the step."""
    data, step = load_print_text(fe)
    at = deck.find("\n*STEP")
    end = deck.rfind("*END STEP")
    if at < 0 or end < at:
        raise ValueError("the deck has no *STEP ... *END STEP to add the load prints to")
    return deck[: at + 1] + data + deck[at + 1 : end] + step + deck[end:]


def _at_time(prints, quantity: str, name: str, time: float):
    """The block of `quantity` (its leading word) for set `name` printed at step time `time` (None if none)."""
    hits = [
        b
        for b in prints
        if b.node_set.upper() == name.upper() and b.quantity.startswith(quantity) and abs(b.time - time) < 1e-9
    ]
    return hits[-1] if hits else None


def element_pressure(stress_block) -> tuple[np.ndarray, np.ndarray]:
    """(element ids (E,), mean hydrostatic pressure -tr(sigma)/3 over each element's integration points, MPa)
    of an *EL PRINT S block (rows: element, integration point, sxx, syy, szz, sxy, sxz, syz)."""
    ids = np.asarray(stress_block.node_ids)
    values = np.asarray(stress_block.values)
    p = -values[:, 1:4].sum(1) / 3.0
    elems, inv = np.unique(ids, return_inverse=True)
    w = integration_weights(values[:, 0].astype(np.int64), np.bincount(inv)[inv])
    return elems, np.bincount(inv, weights=p * w) / np.bincount(inv, weights=w)


#: 3-point Gauss-Legendre weights (C3D20's rule in each direction)
GAUSS3_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 9.0


def integration_weights(point: np.ndarray, points_per_element: np.ndarray) -> np.ndarray:
    """Weight of each printed integration point (1-based `point` of an element with `points_per_element`
    points) in its parent element's rule: the 3 x 3 x 3 Gauss product for 27 points, 1 otherwise."""
    k = np.asarray(point) - 1
    w = GAUSS3_WEIGHTS[k % 3] * GAUSS3_WEIGHTS[(k // 3) % 3] * GAUSS3_WEIGHTS[k // 9 % 3]
    return np.where(np.asarray(points_per_element) == 27, w, 1.0)


def nucleus_pressure(fe: FEModel, prints, time: float) -> pd.DataFrame:
    """Volume-weighted nucleus pressure (MPa) of every disc of `fe` at step time `time`: one row per disc with
    its nucleus volume (mm^3, current) and element count; NaN where the .dat has no print at that time."""
    rows = []
    for name, level in nucleus_sets(fe.element_sets).items():
        s, v = _at_time(prints, "stresses", name, time), _at_time(prints, "volume", name, time)
        if s is None or v is None:
            rows.append((level, np.nan, np.nan, 0))
            continue
        elems, p = element_pressure(s)
        vol = dict(zip(np.asarray(v.node_ids).tolist(), np.asarray(v.values)[:, 0]))
        w = np.array([vol[int(e)] for e in elems])
        rows.append((level, float(p @ w / w.sum()), float(w.sum()), len(elems)))
    return pd.DataFrame(rows, columns=["disc", "pressure_mpa", "volume_mm3", "n_elements"])


def strut_forces_n(x1: np.ndarray, x2: np.ndarray, u1: np.ndarray, u2: np.ndarray, tables) -> np.ndarray:
    """Compression (N, positive) of struts with reference end points x1, x2 (S, 3) mm and displacements u1, u2
    (S, 3) mm: the force of each one's table (force N, elongation mm pairs, ascending) at its elongation
    (current minus reference length), as ccx's SPRINGA interpolates it."""
    elong = np.linalg.norm((x2 + u2) - (x1 + u1), axis=1) - np.linalg.norm(x2 - x1, axis=1)
    out = np.empty(len(elong))
    for i, (e, table) in enumerate(zip(elong, tables)):
        t = np.asarray(table, dtype=np.float64)
        out[i] = -np.interp(e, t[:, 1], t[:, 0])
    return out + 0.0  # no -0.0


def facet_forces(fe: FEModel, prints, time: float) -> pd.DataFrame:
    """Contact force (N, compression positive) of every facet joint side and kind at step time `time`: the sum of
    its struts' forces (`strut_forces_n`) from the FACETNODES displacements; one row per (joint, side, kind) with
    the strut count.  Empty without facet struts; NaN forces where the .dat has no print at that time."""
    struts = facet_struts(fe)
    cols = ["joint", "side", "kind", "n_struts", "force_n"]
    if not len(struts):
        return pd.DataFrame(columns=cols)
    block = _at_time(prints, "displacements", FACET_NODES, time)
    if block is None:
        forces = np.full(len(struts), np.nan)
    else:
        disp = np.zeros((len(fe.nodes), 3))
        disp[np.asarray(block.node_ids) - 1] = block.values
        n1, n2 = struts["node1"].to_numpy(), struts["node2"].to_numpy()
        forces = strut_forces_n(fe.nodes[n1], fe.nodes[n2], disp[n1], disp[n2], struts["table"])
    out = (
        struts.assign(force_n=forces)
        .groupby(["joint", "side", "kind"], sort=False)
        .agg(n_struts=("elset", "size"), force_n=("force_n", lambda f: f.sum(min_count=1)))
        .reset_index()
    )
    return out[cols]
