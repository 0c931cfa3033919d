"""Connectors that make a spine model one mechanical body: stiff linear springs (SPRINGA) joining each
posterior arch to its pedicles' end faces (`spinecohort.fe.pedicles`; without pedicles, to its body's posterior
wall), the sacrum to the S1 plate, the pelvis to the sacrum and each femoral head to the pelvis.

Why connectors: in the template the vertebral bodies and discs are one conforming hex column, but the
posterior elements, sacrum, pelvis and femoral heads are S3 skins of the triangulated shape (each made of
several closed pieces: the posterior skin of a vertebra has 11, the pelvis 12) that share no node with the
hexes; joined only by tension-only ligament springs, the deck is not one body and ccx diverges (largest
displacement increment ~1e15 mm).  Bone is ~10^4 times stiffer than disc and ligament, so each bony part is
attached as rigid: a truss of stiff springs from a few attachment nodes of the part to a set of target nodes
of the part it rests on (every attachment node to every target node, and between the attachment nodes).
A node tied to >= 3 non-coplanar targets is fixed to them; three non-collinear such nodes fix a piece.

The same truss joins the ROM sub-model's arch anchors to the body (`spinecohort.rom.submodel`), so what the
ROM analysis validates is what the exported deck carries.  Springs, not *TIE/*COUPLING/*RIGID BODY: SPRINGA
with a *SPRING, NONLINEAR table is read the same by Abaqus and ccx 2.20, while seven *RIGID BODY arches
stalled ccx's Newton iterations (docs/explanation/fe-model.md) and *TIE needs surfaces.  Units: mm, N.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.mesh.template import HexTemplate

#: axial stiffness (N/mm) of each connector spring: with ~30 springs per attachment node an arch deflects
#: ~0.01 mm under a 100 N ligament force, i.e. it is as good as rigid next to the disc, while the matrix stays
#: well conditioned next to 0.1 MPa soft tissue
CONNECTOR_N_PER_MM = 2000.0


def linear_spring_table(stiffness_n_per_mm: float) -> tuple[tuple[float, float], ...]:
    """A linear SPRINGA force-elongation table (N, mm) of the given stiffness, the same in tension and
    compression, +-100 mm."""
    return ((-stiffness_n_per_mm * 100.0, -100.0), (stiffness_n_per_mm * 100.0, 100.0))


#: the connectors' linear force-elongation table (N, mm)
CONNECTOR_TABLE = linear_spring_table(CONNECTOR_N_PER_MM)
#: target nodes per piece of the pelvis (on the sacrum) and per femoral head (on the pelvis)
NEAREST_TARGETS = 16
#: springs shorter than this (mm) have no defined direction; such a pair is left out
MIN_SPRING_MM = 0.5


def body_layer(template: HexTemplate, level: str, t: float) -> int:
    """Node layer of vertebra `level` at height fraction t (0 inferior, 1 superior endplate); S1: layer 0."""
    if level == "S1":
        return 0
    for i, layer in enumerate(template.layers):
        if layer["kind"] == "body" and layer["level"] == level and abs(layer["t"] - t) < 1e-12:
            return i
    raise KeyError((level, t))


def posterior_wall(template: HexTemplate, level: str, band: float = -0.7) -> np.ndarray:
    """Template node ids of the body's posterior cortical shell (the two outermost rings where the unit
    cross-section has y < band) on its interior node layers (the pedicle base the arch is fixed to)."""
    g = template.grid
    n2, m = len(g.nodes), len(g.outer)
    n_core = n2 - g.shell_ring * m
    post = np.flatnonzero(g.nodes[g.outer][:, 1] < band)
    ring_ids = np.concatenate([n_core + k * m + post for k in (g.shell_ring - 2, g.shell_ring - 1)])
    lo, hi = body_layer(template, level, 0.0), body_layer(template, level, 1.0)
    return (np.arange(lo + 1, hi)[:, None] * n2 + ring_ids[None, :]).ravel()


def skin_nodes(template: HexTemplate, elset: str) -> np.ndarray:
    """Template node ids of the skin triangles of element set `elset` (empty if the template has none)."""
    if elset not in template.elsets:
        return np.zeros(0, dtype=np.int64)
    return np.unique(template.tris[template.elsets[elset]])


def arch_nodes(template: HexTemplate, level: str) -> np.ndarray:
    """Template node ids of the posterior-arch skin of vertebra `level` (empty if it has none)."""
    return skin_nodes(template, f"POST_{level}")


def sacrum_nodes(template: HexTemplate) -> np.ndarray:
    """Template node ids of the sacrum's skin (empty if the template has none)."""
    return skin_nodes(template, "SACRUM")


def arch_owner(template: HexTemplate) -> dict[int, str]:
    """Template node id of every posterior-arch node -> its vertebra, and of every sacrum node -> ``"S1"`` (the
    lower side of the L5-S1 facet joints)."""
    out = {int(n): "S1" for n in sacrum_nodes(template)}
    out.update({int(n): v for v in LEVELS for n in arch_nodes(template, v)})
    return out


def base_nodes(template: HexTemplate, level: str) -> np.ndarray:
    """Template node ids a bony part of `level` hangs on: a vertebra's posterior wall (`posterior_wall`), and for
    ``"S1"`` the S1 plate (the column's bottom node layer), which carries the sacrum (``CONN_SACRUM``)."""
    if level == "S1":
        return np.arange(len(template.grid.nodes))
    return posterior_wall(template, level)


def truss_pairs(attach: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(P, 2) node pairs of a rigid attachment: every attachment node to every target node, then every pair
    of attachment nodes (upper triangle, row-major)."""
    attach, target = np.asarray(attach, dtype=np.int64), np.asarray(target, dtype=np.int64)
    ii, jj = np.triu_indices(len(attach), 1)
    return np.concatenate(
        [np.stack(np.meshgrid(attach, target, indexing="ij"), -1).reshape(-1, 2), np.stack([attach[ii], attach[jj]], 1)]
    )


def skin_pieces(template: HexTemplate, elset: str) -> list[np.ndarray]:
    """Node ids of each edge-connected piece of a skin (S3) element set, largest first (ties by first id)."""
    tris = template.tris[template.elsets[elset]]
    nodes = np.unique(tris)
    loc = np.searchsorted(nodes, tris)
    e = np.concatenate([loc[:, [0, 1]], loc[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(nodes), len(nodes)))
    n, label = connected_components(graph, directed=False)
    pieces = [nodes[label == k] for k in range(n)]
    return sorted(pieces, key=lambda p: (-len(p), int(p[0])))


def spread_nodes(points: np.ndarray, piece: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Three well-spread node ids of a piece: the one nearest `towards` (mm), the one farthest from it and
    the one farthest from the line through those two (non-collinear, so the three fix the piece)."""
    p = points[piece]
    a = int(np.argmin(np.linalg.norm(p - towards, axis=1)))
    b = int(np.argmax(np.linalg.norm(p - p[a], axis=1)))
    d = (p[b] - p[a]) / max(np.linalg.norm(p[b] - p[a]), 1e-12)
    off = (p - p[a]) - np.outer((p - p[a]) @ d, d)
    c = int(np.argmax(np.linalg.norm(off, axis=1)))
    return piece[np.unique([a, b, c])]


def nearest_targets(points: np.ndarray, piece: np.ndarray, candidates: np.ndarray, k: int) -> np.ndarray:
    """The `k` candidate node ids closest (mm) to any node of the piece, sorted by id."""
    dist, _ = cKDTree(points[piece]).query(points[candidates])
    return np.sort(candidates[np.argsort(dist, kind="stable")[:k]])


def drop_short(points: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """The spring pairs at least MIN_SPRING_MM long (a zero-length SPRINGA stops ccx: springforc_n2f)."""
    length = np.linalg.norm(points[pairs[:, 1]] - points[pairs[:, 0]], axis=1)
    return pairs[length >= MIN_SPRING_MM]


def model_connectors(
    template: HexTemplate, points: np.ndarray, bases: dict[str, np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """Connector springs of the whole model as {element set name: (P, 2) template node pairs}:

    * ``CONN_ARCH_<lvl>``: the posterior skin of each vertebra to its body's posterior wall; attachment
      nodes = every ligament end on the arch (the ROM's arch anchors) plus three spread nodes per piece;
    * ``CONN_SACRUM``: the sacrum to the S1 plate (the column's bottom node layer); attachment nodes = three
      spread nodes per piece plus every ligament end on the sacrum (L5-S1's posterior ligaments);
    * ``CONN_PELVIS``: each piece of the pelvis to its nearest sacrum nodes (sacroiliac joints);
    * ``CONN_FH_L`` / ``CONN_FH_R``: each femoral head to its nearest pelvis nodes (hip joints).

    bases: level -> the node ids an arch hangs on instead of its posterior wall (the pedicles' end faces,
    `spinecohort.fe.pedicles`), with `points` holding their coordinates (ids beyond the template's nodes).
    The pairs depend on the coordinates only through the choice of attachment and target nodes, which is
    made on `points` (use the template's own nodes so every model of the cohort has the same deck)."""
    bases = bases or {}
    points = np.asarray(points, dtype=np.float64)
    lig_ends = np.unique(template.ligaments)
    out: dict[str, np.ndarray] = {}
    for v in LEVELS:
        if f"POST_{v}" not in template.elsets:
            continue
        wall = posterior_wall(template, v)
        centre = points[wall].mean(0)
        spread = [spread_nodes(points, p, centre) for p in skin_pieces(template, f"POST_{v}")]
        anchors = np.intersect1d(arch_nodes(template, v), lig_ends)
        attach = np.concatenate([anchors, np.setdiff1d(np.concatenate(spread), anchors)])
        out[f"CONN_ARCH_{v}"] = drop_short(points, truss_pairs(attach, bases.get(v, wall)))
    s1_plate = np.arange(len(template.grid.nodes))
    if "SACRUM" in template.elsets:
        centre = points[s1_plate].mean(0)
        pairs = [truss_pairs(spread_nodes(points, p, centre), s1_plate) for p in skin_pieces(template, "SACRUM")]
        # the sacrum's ligament ends (L5-S1's posterior ligaments), each tied to the plate like an arch's anchors
        anchors = np.intersect1d(sacrum_nodes(template), lig_ends)
        if len(anchors):
            pairs.append(truss_pairs(anchors, s1_plate))
        out["CONN_SACRUM"] = drop_short(points, np.concatenate(pairs))
    for part, base in (("PELVIS", "SACRUM"), ("FH_L", "PELVIS"), ("FH_R", "PELVIS")):
        if part not in template.elsets or base not in template.elsets:
            continue
        candidates = np.unique(template.tris[template.elsets[base]])
        pairs = []
        for piece in skin_pieces(template, part):
            target = nearest_targets(points, piece, candidates, NEAREST_TARGETS)
            pairs.append(truss_pairs(spread_nodes(points, piece, points[target].mean(0)), target))
        out[f"CONN_{part}"] = drop_short(points, np.concatenate(pairs))
    return out
