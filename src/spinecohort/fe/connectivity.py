"""Is a deck one mechanical body?  Every element must be reachable from the fixed nodes through elements
that carry load both ways (solids, shells, trusses, linear springs such as the connectors) and through
rigid bodies / couplings; one-sided springs (tension-only ligaments, compression-only facet struts) and gap
elements do not count, because a part held only by them floats as soon as they go slack (the failure the exported decks had: ccx diverged with
displacement increments of ~1e15 mm).  Graph components by `scipy.sparse.csgraph.connected_components`.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from spinecohort.fe.abaqus import FEModel

#: element types that never join two parts (a gap transmits only when closed)
NON_CONNECTING_TYPES = {"GAPUNI"}


class ConnectivityError(ValueError):
    """A deck has parts that are not connected to its fixed nodes."""


def one_sided_sets(model: FEModel) -> set[str]:
    """Upper-case names of the one-sided SPRINGA sections: tension only (the table's first row, the smallest
    elongation, is (0, <= 0): a ligament) or compression only (its last row is (0, >= 0): a facet contact
    strut, `spinecohort.fe.facets.strut_table`); ccx holds the force beyond the table's ends, so such a spring
    carries nothing on one side and never joins two parts for certain.  A ligament (set ``LIG_*``) counts as one
    even when taut in the neutral posture (`spinecohort.fe.ligament_curves`): it pushes only until it has given
    back the tension it held there."""
    out = set()
    for sec in model.sections:
        table = sec.spring_force_elongation
        if table is None:
            continue
        ligament = sec.elset.upper().startswith("LIG_")
        if ligament or (table[0][0] == 0.0 and table[0][1] <= 0.0) or (table[-1][0] == 0.0 and table[-1][1] >= 0.0):
            out.add(sec.elset.upper())
    return out


def _connecting_mask(model: FEModel) -> np.ndarray:
    """(E,) bool: element carries load both ways (see the module docstring)."""
    keep = np.ones(model.n_elements, bool)
    offsets = model.block_offsets()
    for name, (etype, conn) in model.element_blocks.items():
        if etype in NON_CONNECTING_TYPES:
            keep[offsets[name] : offsets[name] + len(conn)] = False
    slack = one_sided_sets(model)
    for name, (_, conn) in model.element_blocks.items():
        if name.upper() in slack:
            keep[offsets[name] : offsets[name] + len(conn)] = False
    for name, idx in model.element_sets.items():
        if name.upper() in slack:
            keep[np.asarray(idx)] = False
    return keep


def reachable_nodes(model: FEModel, fixed_nodes: np.ndarray, couplings: Iterable[np.ndarray] = ()) -> np.ndarray:
    """(N,) bool: node is connected to a fixed node through connecting elements and couplings (each a set of
    0-based node indices moving together: *RIGID BODY, *COUPLING, *TIE or *EQUATION node groups)."""
    n = len(model.nodes)
    keep = _connecting_mask(model)
    rows, cols, start = [], [], 0
    for _, conn in model.element_blocks.values():
        conn = np.asarray(conn, dtype=np.int64)
        sel = conn[keep[start : start + len(conn)]]
        start += len(conn)
        if len(sel):  # a star from each element's first node joins all its nodes
            rows.append(np.repeat(sel[:, 0], sel.shape[1] - 1))
            cols.append(sel[:, 1:].ravel())
    for ties, _ in model.ties():  # an *EQUATION tie joins its nodes
        rows.append(np.repeat(ties[:, 0], ties.shape[1] - 1))
        cols.append(ties[:, 1:].ravel())
    for group in couplings:
        group = np.asarray(group, dtype=np.int64)
        rows.append(np.full(len(group) - 1, group[0]))
        cols.append(group[1:])
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    fixed = np.asarray(fixed_nodes, dtype=np.int64)
    if fixed.size == 0:
        raise ConnectivityError("no fixed nodes given: nothing to be connected to")
    return np.isin(label, np.unique(label[fixed]))


def unreachable_report(model: FEModel, fixed_nodes: np.ndarray, couplings: Iterable[np.ndarray] = ()) -> dict[str, int]:
    """{element set or block name: number of its elements with a node not connected to the fixed nodes};
    empty when the model is one body.  An element is named by the smallest element set holding it (e.g.
    ``POST_L3`` rather than the block ``SURFACES``)."""
    ok = reachable_nodes(model, fixed_nodes, couplings)
    bad = np.zeros(model.n_elements, bool)
    start = 0
    for _, conn in model.element_blocks.values():
        conn = np.asarray(conn, dtype=np.int64)
        bad[start : start + len(conn)] = ~ok[conn].all(axis=1)
        start += len(conn)
    if not bad.any():
        return {}
    owner = np.full(model.n_elements, "", dtype=object)
    size = np.full(model.n_elements, np.iinfo(np.int64).max)
    offsets = model.block_offsets()
    named = [(name, np.arange(offsets[name], offsets[name] + len(c))) for name, (_, c) in model.element_blocks.items()]
    named += [(name, np.asarray(idx)) for name, idx in model.element_sets.items()]
    for name, idx in named:
        better = size[idx] > len(idx)
        owner[idx[better]] = name
        size[idx[better]] = len(idx)
    names, counts = np.unique(owner[bad].astype(str), return_counts=True)
    return dict(zip(names.tolist(), counts.tolist()))


def check_connected(model: FEModel, fixed_nodes: np.ndarray, deck: str, couplings: Iterable[np.ndarray] = ()) -> None:
    """Raise ConnectivityError naming the deck and its unconnected parts unless every element is reachable
    from `fixed_nodes` (0-based) through connecting elements and `couplings`."""
    report = unreachable_report(model, fixed_nodes, couplings)
    if report:
        parts = ", ".join(f"{k} ({v} elements)" for k, v in sorted(report.items()))
        raise ConnectivityError(
            f"deck {deck}: {sum(report.values())} of {model.n_elements} elements are not connected to the "
            f"fixed nodes through load-carrying elements, connectors or couplings (tension-only ligaments and "
            f"gaps do not count): {parts}"
        )
