"""Hexahedral pedicles: the bone that joins each posterior arch to its vertebral body.

Per vertebra and side, a structured block of C3D8 hexes runs from a patch of the body's outer cortical wall (the
body's own hex nodes, so the block is conforming with the body) along the pedicle to its posterior end, where
the arch begins; the arch (its S3 skin and its ligament and facet anchors, rigid next to the disc) is held by the
pedicles' end faces instead of the body's posterior wall.  The load between a body and its arch therefore passes
through bone of the pedicles' length and cross-section, as in the specimen.

Geometry, on a model's own points (mm), from the labeled pedicle of the reference (``pedicle_<side>/<level>``
template sites, `spinecohort.cohort.real.reference_sites`):

* the labeled pedicle is the ring where the pedicle leaves the body (the root); its centre starts the **axis**,
  which runs back in the body's transverse plane to the articular pillar (the mean of the side's superior and
  inferior articular surfaces), where the lamina and the articular processes meet: the block's end face is
  centred there;
* the **cross-section** is the root's width (lateral) and height (along the body's axis), robust to stray
  labels (`ring_radius`), at least `MIN_SECTION_MM` each way;
* the **base** is the quad patch of the body's outermost ring nearest the root, as many whole quads around and
  high as fit in the root (at least one), chosen on the template's own nodes so every model of the cohort has
  the same elements.

A cohort without pedicle sites (the primitive generator) has no pedicles: its arches hang on the posterior wall
by the connector truss (`spinecohort.fe.connections`).  Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.fe.connections import body_layer
from spinecohort.mesh.template import HexTemplate

SIDES = ("left", "right")
#: smallest pedicle section half-extent (mm): a labeled strip narrower than this still gets a solid pedicle
MIN_SECTION_MM = 2.0
#: shortest pedicle (mm), the root's centre to the pillar in the transverse plane: a shorter one is an error in the labels
MIN_LENGTH_MM = 3.0


@dataclass(frozen=True)
class Pedicles:
    """The pedicle blocks of a model.  Node ids: the body's template node ids, and the new nodes from ``first_id``
    on (``points`` in that order)."""

    first_id: int  # id of the first new node
    points: np.ndarray  # (P, 3) mm, the new nodes
    hexes: np.ndarray  # (H, 8) C3D8 node order, ids as above
    elsets: dict[str, np.ndarray] = field(default_factory=dict)  # "PED_<lvl>_<L|R>" -> rows of hexes
    ends: dict[str, np.ndarray] = field(default_factory=dict)  # level -> node ids of both end faces (the arch's base)
    nodes_of: dict[str, np.ndarray] = field(default_factory=dict)  # level -> every node id of its pedicles

    @property
    def levels(self) -> list[str]:
        return list(self.ends)


def has_pedicles(template: HexTemplate, level: str) -> bool:
    """Whether the template carries the labeled pedicles of `level` (and both facet pillars, their direction)."""
    need = [f"pedicle_{s}/{level}" for s in SIDES]
    need += [f"facet_surface_{w}_{s}/{level}" for w in ("sup", "inf") for s in SIDES]
    return all(k in template.sites and len(template.sites[k]) for k in need)


def outer_ring(template: HexTemplate) -> np.ndarray:
    """Cross-section node ids of the outermost ring (the cortical surface), counter-clockwise, one per ray."""
    g = template.grid
    m = len(g.outer)
    n_core = len(g.nodes) - g.shell_ring * m
    return n_core + (g.shell_ring - 1) * m + np.arange(m)


@dataclass(frozen=True)
class _Frame:
    root: np.ndarray  # the labeled root's centre (mm)
    axis: np.ndarray  # unit, from the root towards the articular pillar
    lateral: np.ndarray  # unit, across the axis
    cranial: np.ndarray  # unit, across the axis
    end: np.ndarray  # the end face's centre (mm): the articular pillar
    half: tuple[float, float]  # half-width (lateral), half-height (cranial) of the root, mm


def body_axes(template: HexTemplate, points: np.ndarray, level: str) -> tuple[np.ndarray, np.ndarray]:
    """The body's centre (mm) and unit cranial axis (inferior to superior endplate centre)."""
    inf, sup = (body_layer(template, level, t) for t in (0.0, 1.0))
    n2 = len(template.grid.nodes)
    lo, hi = points[inf * n2 : (inf + 1) * n2].mean(0), points[sup * n2 : (sup + 1) * n2].mean(0)
    return 0.5 * (lo + hi), (hi - lo) / np.linalg.norm(hi - lo)


def pedicle_frame(template: HexTemplate, points: np.ndarray, level: str, side: str) -> _Frame:
    """Axis, end and root section (`_Frame`) of one pedicle on `points`.  The labeled pedicle is the ring where
    the pedicle leaves the body; it runs back in the body's transverse plane to the articular pillar (the mean of
    the side's superior and inferior articular surfaces), where the lamina and the articular processes meet."""
    ring = points[template.sites[f"pedicle_{side}/{level}"]]
    root = ring.mean(0)
    pillar = np.mean([points[template.sites[f"facet_surface_{w}_{side}/{level}"]].mean(0) for w in ("sup", "inf")], 0)
    up = body_axes(template, points, level)[1]
    axis = pillar - root
    axis -= (axis @ up) * up
    length = float(np.linalg.norm(axis))
    if length < MIN_LENGTH_MM:
        raise ValueError(f"the {side} pedicle of {level} is shorter than {MIN_LENGTH_MM} mm (root to pillar)")
    axis /= length
    lateral = np.cross(up, axis)
    half = tuple(max(ring_radius((ring - root) @ e), MIN_SECTION_MM) for e in (lateral, up))
    return _Frame(root, axis, lateral, up, root + length * axis, half)


def ring_radius(x: np.ndarray) -> float:
    """Half-extent (mm) of a ring's nodes projected on a line, robust to stray labels: the 20-80 percentile
    spread of a circle of radius r is 1.618 r."""
    lo, hi = np.percentile(x, [20, 80])
    return float(hi - lo) / (2.0 * np.cos(np.pi / 5))


def base_patch(template: HexTemplate, level: str, side: str, points: np.ndarray) -> np.ndarray:
    """(h + 1, w + 1) template node ids of the body-wall patch a pedicle starts from: centred where the labeled
    root's centre is nearest the outer ring, as many quads around and high as the root is wide and high (at least
    one); rows run cranially, columns counter-clockwise around the body.  Chosen on `points` (the template's own
    nodes, for one deck per cohort)."""
    ring = outer_ring(template)
    m, n2 = len(ring), len(template.grid.nodes)
    inf, sup = (body_layer(template, level, t) for t in (0.0, 1.0))
    wall = np.arange(inf, sup + 1)[:, None] * n2 + ring[None, :]  # (layers, m)
    fr = pedicle_frame(template, points, level, side)
    d = np.linalg.norm(points[wall] - fr.root, axis=2)
    li, j = np.unravel_index(np.argmin(d), d.shape)
    quad_w = 0.5 * np.linalg.norm(points[wall[li, (j + 1) % m]] - points[wall[li, (j - 1) % m]])
    layer_h = np.abs(np.diff((points[wall[:, j]] - fr.root) @ fr.cranial)).mean()
    # whole quads inside the root (a rounded-up patch of the root's outline reached the canal's mid-line at L3)
    w = int(np.clip(2 * fr.half[0] // quad_w, 1, m // 4))
    h = int(np.clip(2 * fr.half[1] // layer_h, 1, len(wall) - 1))
    # centred on the root's nearest column; an odd count puts its extra quad on the side nearer the root's centre
    j0 = int(j) - w // 2 - (w % 2 and d[li, (j + 1) % m] > d[li, (j - 1) % m])
    z = (points[wall[:, j]] - fr.root) @ fr.cranial
    l0 = int(np.clip(np.argmin(np.abs(z + 0.5 * h * layer_h)), 0, len(wall) - 1 - h))
    return wall[l0 : l0 + h + 1][:, (j0 + np.arange(w + 1)) % m]


def pedicle_blocks(
    template: HexTemplate,
    points: np.ndarray,
    layers: int = 3,
    choose_on: np.ndarray | None = None,
    first_id: int | None = None,
    levels: tuple[str, ...] = LEVELS,
) -> Pedicles:
    """The pedicles of every vertebra of `levels` that has them (`has_pedicles`) on `points` (template node order,
    mm): `layers` hexes along each pedicle; the base patches are chosen on `choose_on` (default the template's own
    nodes).  first_id: the id of the first new node (default: right after the template's nodes)."""
    points = np.asarray(points, dtype=np.float64)
    choose = template.nodes if choose_on is None else choose_on
    n = len(points) if first_id is None else int(first_id)
    new_pts, hexes, names, ends, nodes_of = [], [], [], {}, {}
    count = 0
    for v in levels:
        if not has_pedicles(template, v):
            continue
        level_ends, level_nodes = [], []
        for side in SIDES:
            patch = base_patch(template, v, side, choose)  # (h+1, w+1)
            hp, wp = patch.shape
            base = points[patch]
            fr = pedicle_frame(template, points, v, side)
            # the end face: the patch's own (column, row) grid spread over the pedicle's end section
            u = np.linspace(-1.0, 1.0, wp)[None, :, None]
            w_ = np.linspace(-1.0, 1.0, hp)[:, None, None]
            # the end face keeps the patch's handedness: its columns spread the way the patch's columns run
            col_dir = np.sign((base[:, -1] - base[:, 0]).mean(0) @ fr.lateral) or 1.0
            end = fr.end + col_dir * u * fr.half[0] * fr.lateral + w_ * fr.half[1] * fr.cranial
            t = np.linspace(0.0, 1.0, layers + 1)[:, None, None, None]
            grid = (1 - t) * base[None] + t * end[None]  # (layers+1, h+1, w+1, 3)
            ids = np.empty(grid.shape[:3], dtype=np.int64)
            ids[0] = patch
            k = grid[1:].reshape(-1, 3)
            ids[1:] = (n + count + np.arange(len(k))).reshape(grid[1:].shape[:3])
            new_pts.append(k)
            count += len(k)
            a, b, c, d = ids[:, :-1, :-1], ids[:, :-1, 1:], ids[:, 1:, 1:], ids[:, 1:, :-1]
            blk = np.stack([a[:-1], b[:-1], c[:-1], d[:-1], a[1:], b[1:], c[1:], d[1:]], -1).reshape(-1, 8)
            names.append(f"PED_{v}_{side[0].upper()}")
            hexes.append(blk)
            level_ends.append(ids[-1].ravel())
            level_nodes.append(ids[1:].ravel())
        ends[v] = np.concatenate(level_ends)
        nodes_of[v] = np.concatenate(level_nodes)
    pts = np.concatenate(new_pts) if new_pts else np.zeros((0, 3))
    first = np.cumsum([0] + [len(b) for b in hexes])
    elsets = {name: np.arange(first[i], first[i + 1]) for i, name in enumerate(names)}
    allh = np.concatenate(hexes) if hexes else np.zeros((0, 8), dtype=np.int64)
    every = np.zeros((n + len(pts), 3))
    every[: len(points)], every[n:] = points, pts
    allh = positive_order(every, allh)
    return Pedicles(n, pts, allh, elsets, ends, nodes_of)


def model_pedicles(
    template: HexTemplate, points: np.ndarray, layers: int | None, first_id: int, levels: tuple[str, ...] = LEVELS
) -> tuple[Pedicles, Pedicles] | None:
    """The pedicles of a model on its `points` and the same elements on the template's own nodes (where a deck's
    coordinate-free choices, such as the arch truss's short springs, are made), new nodes from `first_id`; None
    without pedicles (`layers` None, or a cohort without labeled pedicles)."""
    if not layers or not any(has_pedicles(template, v) for v in levels):
        return None
    on_model = pedicle_blocks(template, points, layers, first_id=first_id, levels=levels)
    on_template = pedicle_blocks(template, template.nodes, layers, first_id=first_id, levels=levels)
    return on_model, on_template


def add_block(blocks: dict, elsets: dict, sections: list, hexes: np.ndarray, pedicle_sets: dict) -> None:
    """Append the pedicles as the model's next element block ``PEDICLES`` (C3D8, material POSTERIOR), their element
    sets numbered after every element already in `blocks`; hexes: in the model's node ids."""
    from spinecohort.fe.abaqus import Section
    from spinecohort.fe.materials import POSTERIOR_BONE

    first = sum(len(c) for _, c in blocks.values())
    blocks["PEDICLES"] = ("C3D8", hexes)
    for name, rows in pedicle_sets.items():
        elsets[name] = first + rows
        sections.append(Section(elset=name, material=POSTERIOR_BONE))


def positive_order(points: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """The hexes with their two faces swapped where the node order gives a negative volume (C3D8 needs the
    bottom face counter-clockwise seen from the top)."""
    if not len(hexes):
        return hexes
    p = points[hexes]
    jac = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 3] - p[:, 0]), p[:, 4] - p[:, 0])
    out = hexes.copy()
    flip = jac < 0
    out[flip] = hexes[flip][:, [4, 5, 6, 7, 0, 1, 2, 3]]
    return out
