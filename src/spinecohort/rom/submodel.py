"""The ROM sub-model of a hex spine model: the vertebrae ``top`` ... ``bottom`` with their discs, ligaments,
posterior-arch trusses and facet-joint contact struts, renumbered compactly, plus what the analysis needs to
load it (the rigid top, the fixed bottom) and to read it (endplate node layers, anatomical frames).

Units: mm, N, N.mm, degrees.

What a ROM model contains (`extract_rom_model`): the conforming hex column of the bodies and the discs
between them, every ligament whose two ends lie on the kept vertebrae and (optionally) one facet-joint gap
element per joint.  Elements: C3D8 for bone and cartilage endplates, C3D8R for the disc soft tissue
(docs/explanation/fe-model.md "Elements": C3D8/C3D8I abort ccx 2.20's fibre law in the annulus, and a fully integrated
C3D8 locks the nearly incompressible nucleus in bending).
The posterior elements are S3 skins in the template and share no node with the hex bodies; bone is ~10^4
times stiffer than disc and ligament, so each posterior arch is modelled as rigid: a stiff truss joins its
ligament/facet anchor nodes to each other and to the end faces of its two hex pedicles (`spinecohort.fe.pedicles`,
bone from the body's cortical wall to the articular pillars; a cohort without labeled pedicles: to the body's
posterior cortical-shell nodes between its endplates) -- the truss of `spinecohort.fe.connections`, the one the
exported deck carries (there with the skins' own attachment nodes added); the skin elements themselves carry
nothing here and are left out.  The sacrum and
pelvis are fixed in vitro and here: a lumbar model fixes the S1 plate (the bottom node layer of the column);
a functional unit fixes its whole lower vertebra (potting).  The moment acts on the top vertebra, potted
too: one *RIGID BODY of its body and arch anchors (`spinecohort.rom.deck`).

Facet joints (`spinecohort.fe.facets`, the same contacts as the exported decks): per joint a contact strut
and, if configured, an extension stop of the inferior articular process tip on the lamina below; stand-ins for
surface contact, which the S3 skins cannot provide here.

A model down to S1 keeps L5-S1's posterior ligaments and facet joints where the template has them (the sacrum's
anchors, `spinecohort.anatomy.sacrum`): their nodes on the sacrum are fixed with the S1 plate (the sacrum is
potted with the pelvis in vitro).

Limitations (docs/explanation/fe-model.md "Limitations"): facet contact is point gaps, not surface contact; no
iliolumbar ligament; no rib cage (thoracic units).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.fe.abaqus import SOLID_TYPES, FEModel, Section
from spinecohort.fe.connections import (
    CONNECTOR_TABLE,
    arch_nodes,
    body_layer,
    drop_short,
    linear_spring_table,
    posterior_wall,
    sacrum_nodes,
    truss_pairs,
)
from spinecohort.fe.export import add_fibres, annulus_fibres, disc_orientations, hex_blocks, hex_section
from spinecohort.fe.facets import FacetContact, facet_nodes, facet_pairs, vertebra_frame
from spinecohort.fe.ligament_curves import ligament_segments
from spinecohort.fe.materials import (
    DEFAULT_MATERIALS,
    FEMaterials,
    annulus_ring_sets,
    material_cards,
    spring_table,
)
from spinecohort.fe.pedicles import add_block, model_pedicles
from spinecohort.fe.potting import potted_plate
from spinecohort.fe.quadratic import quadratic_blocks, ties_on
from spinecohort.mesh.template import LIGAMENT_GROUPS, HexTemplate, fit_endplate
from spinecohort.rom.ribs import RibHeads, rib_head_nodes

COLUMN = LEVELS + ("S1",)


class RomError(RuntimeError):
    """A ROM analysis cannot run (bad model, inverted element, solver failure)."""


@dataclass
class RomModel:
    """A ROM submodel: its FE model (0-based indices) and what the analysis needs to load and read it."""

    fe: FEModel
    vertebrae: list[str]  # cranial -> caudal; the last one ("S1" or a vertebra) is fixed
    endplate_nodes: dict[str, np.ndarray]  # vertebra -> its two endplate node layers (Kabsch)
    rigid_nodes: dict[str, np.ndarray]  # the loaded top vertebra -> nodes of its rigid body
    fixed_nodes: np.ndarray
    frames: dict[str, np.ndarray]  # vertebra -> (3, 3) columns lateral, anterior, cranial (reference)
    hex_elements: np.ndarray  # element indices (into fe's concatenated blocks) of the hexes
    source_nodes: np.ndarray  # template node index of every submodel node (-1: a facet contact node)
    ligament_groups: dict[str, int] = field(default_factory=dict)  # group -> element count

    @property
    def top(self) -> str:
        return self.vertebrae[0]

    def segments(self) -> list[tuple[str, str]]:
        return list(zip(self.vertebrae[:-1], self.vertebrae[1:]))


def column_levels(top: str, bottom: str) -> list[str]:
    """Vertebrae from ``top`` down to ``bottom`` (``S1`` allowed), cranial first."""
    if top not in LEVELS or bottom not in COLUMN or COLUMN.index(bottom) <= COLUMN.index(top):
        raise ValueError(f"ROM segment {top}..{bottom}: need a vertebra T1..L5 above a vertebra or S1")
    return list(COLUMN[COLUMN.index(top) : COLUMN.index(bottom) + 1])


def parse_unit(name: str) -> tuple[str, str]:
    """'T10T11' or 'T10-T11' -> ('T10', 'T11')."""
    import re

    m = re.fullmatch(r"([TL]\d{1,2})-?([TL]\d{1,2}|S1)", name)
    if not m:
        raise ValueError(f"'{name}' is not a functional unit like T10T11 or L5S1")
    return m[1], m[2]


def extract_rom_model(
    template: HexTemplate,
    points: np.ndarray,
    top: str,
    bottom: str,
    materials: FEMaterials | None = None,
    hex_type: str = "C3D8",
    include_all: bool | None = None,
    heading: str = "",
    ligament_groups: tuple[str, ...] | None = None,
    disc_hex_type: str | None = "C3D8R",
    facets: FacetContact | None = None,
    ribs: RibHeads | None = None,
    nucleus_hex_type: str | None = "C3D20R",
) -> RomModel:
    """The ROM submodel of vertebrae ``top``..``bottom`` (see the module docstring) with the model's
    coordinates ``points`` (N, 3) mm in template node order.

    hex_type: element of bone and cartilage endplates; disc_hex_type: element of the annulus (None: the same as
    hex_type); nucleus_hex_type: element of the nucleus (None: the annulus'); see docs/explanation/fe-model.md for
    why they differ.
    ligament_groups: the groups to keep (default all, ALL per ``include_all``); () = discs alone.
    facets: facet-joint contact, a strut (or GAPUNI) per facet joint and stop (`FacetContact`); None = no contact.
    ribs: the specimens' rib heads as springs (`spinecohort.rom.ribs`); None = none (a spine without ribs)."""
    mats = DEFAULT_MATERIALS if materials is None else materials
    include_all = mats.include_all if include_all is None else include_all
    points = np.asarray(points, dtype=np.float64)
    if points.shape != template.nodes.shape:
        raise ValueError(f"points have shape {points.shape}, the template has {template.nodes.shape}")
    verts = column_levels(top, bottom)
    n2, nq = len(template.grid.nodes), len(template.grid.quads)
    lo = 0 if bottom == "S1" else body_layer(template, bottom, 0.0)
    hi = body_layer(template, top, 1.0)
    hex_ids = (np.arange(lo, hi)[:, None] * nq + np.arange(nq)[None, :]).ravel()
    hex_nodes = np.arange(lo * n2, (hi + 1) * n2)
    bones = [v for v in verts if v != "S1"]
    arch = {v: arch_nodes(template, v) for v in bones}
    # ligaments whose two ends are on the kept hex layers or on the kept arches
    lig_group = np.empty(len(template.ligaments), dtype=object)
    for g in LIGAMENT_GROUPS:
        lig_group[template.elsets[f"LIG_{g}"]] = g
    allowed = np.zeros(len(template.nodes), bool)
    allowed[hex_nodes] = True
    for v in bones:
        allowed[arch[v]] = True
    # a model down to S1: the sacrum's ends of L5-S1's ligaments and facet joints, fixed with the S1 plate
    sacral = np.zeros(0, dtype=np.int64)
    if bottom == "S1":
        ends = [template.ligaments.ravel(), template.sites.get("facet_joints", np.zeros((0, 2), np.int64)).ravel()]
        sacral = np.intersect1d(sacrum_nodes(template), np.concatenate(ends))
        allowed[sacral] = True
    keep_lig = allowed[template.ligaments].all(axis=1)
    if not include_all:
        keep_lig &= lig_group != "ALL"
    if ligament_groups is not None:
        keep_lig &= np.isin(lig_group, list(ligament_groups))
    ligs = template.ligaments[keep_lig]
    groups = lig_group[keep_lig]
    lig_segments = ligament_segments(template)[keep_lig]
    # facet joints: the capsular-ligament anchors (IAP tip of the upper vertebra, SAP tip of the lower one) of
    # every segment in the model (`spinecohort.fe.facets`)
    joints = facet_pairs(template, allowed) if facets is not None else np.zeros((0, 2), dtype=np.int64)
    segments = [(u, lo_) for u, lo_ in zip(bones[:-1], bones[1:])]
    rn = rib_head_nodes(template, points, segments, ribs) if ribs is not None else None
    # arch anchors actually used, per vertebra (ligament ends, and the transverse-process tips of the ribs)
    anchors = {v: np.intersect1d(arch[v], ligs.ravel()) for v in bones}
    anchors["S1"] = np.intersect1d(sacral, np.concatenate([ligs.ravel(), joints.ravel()]))
    if rn is not None:
        for v, tips in rn.tp_tips.items():
            anchors[v] = np.union1d(anchors[v], tips)
    surf = np.unique(np.concatenate([np.zeros(0, np.int64), *anchors.values()]))
    source = np.concatenate([hex_nodes, surf])
    new_of = np.full(len(template.nodes), -1, dtype=np.int64)
    new_of[source] = np.arange(len(source))
    pts = points[source]
    extra_tied: dict[str, np.ndarray] = {v: np.zeros(0, np.int64) for v in bones}
    facet_conn = np.zeros((0, 2), dtype=np.int64)
    fn = None
    if len(joints):
        fn = facet_nodes(template, points, joints, facets)
        first_new = len(pts)
        pts = np.concatenate([pts, fn.points])
        for v, ix in fn.tied.items():
            extra_tied[v] = first_new + ix
        facet_conn = first_new + fn.gaps
        source = np.concatenate([source, np.full(len(fn.points), -1)])
    rib_conn = np.zeros((0, 2), dtype=np.int64)
    if rn is not None and len(rn.points):
        first_new = len(pts)
        pts = np.concatenate([pts, rn.points])
        rib_conn = np.stack([first_new + rn.springs[:, 0], new_of[rn.springs[:, 1]]], 1)
        source = np.concatenate([source, np.full(len(rn.points), -1)])

    # the pedicles of the kept vertebrae (`spinecohort.fe.pedicles`): bone from each body to its arch's base
    n_tpl = len(template.nodes)
    peds = model_pedicles(template, points, mats.pedicle_layers, n_tpl, tuple(bones))
    first_ped = len(pts)
    if peds is not None:
        pts = np.concatenate([pts, peds[0].points])
        source = np.concatenate([source, np.full(len(peds[0].points), -1)])

    def ped_ids(ids: np.ndarray) -> np.ndarray:  # pedicle node ids (template ids, new from n_tpl) -> submodel ids
        return np.where(ids < n_tpl, new_of[np.minimum(ids, n_tpl - 1)], first_ped + ids - n_tpl)

    # disc soft-tissue hexes (annulus, nucleus) last, in their own blocks when their element types differ
    hex_ids, tpl_blocks = hex_blocks(template, hex_ids, hex_type, disc_hex_type, nucleus_hex_type)
    blocks = {name: (etype, new_of[conn]) for name, (etype, conn) in tpl_blocks.items()}
    n_hexes = len(hex_ids)
    lig_conn = new_of[ligs]
    # quadratic hexes (the nucleus), conforming to their linear neighbours by midside ties (`spinecohort.fe.quadratic`;
    # docs/explanation/fe-model.md: C3D8R discs leak moment, C3D8 locks the nucleus)
    n_before = len(pts)
    pts, blocks, ties = quadratic_blocks(pts, blocks)
    source = np.concatenate([source, np.full(len(pts) - n_before, -1)])
    elsets: dict[str, np.ndarray] = {}
    pos_of_hex = np.full(len(template.hexes), -1, dtype=np.int64)
    pos_of_hex[hex_ids] = np.arange(len(hex_ids))
    orientations = disc_orientations(template, points)
    sections, used_orient = [], set()
    ring_sets = annulus_ring_sets(template, mats)  # the annulus per ring when k1 is graded, as in the export
    for name, idx in template.elsets.items():
        if template.elset_kind[name] != "hex":
            continue
        for set_name, set_idx in ring_sets.get(name, {name: idx}).items():
            sub = pos_of_hex[set_idx]
            sub = sub[sub >= 0]
            if len(sub) == 0:
                continue
            elsets[set_name] = np.sort(sub)
            sec = hex_section(set_name, None if mats.fibre_springs else orientations)
            sections.append(sec)
            if sec.orientation:
                used_orient.add(sec.orientation)
    lig_counts: dict[str, int] = {}
    if len(lig_conn):
        blocks["LIGAMENTS"] = ("SPRINGA", lig_conn)
        rest = np.linalg.norm(pts[lig_conn[:, 1]] - pts[lig_conn[:, 0]], axis=1)
        for i, (g, seg, length) in enumerate(zip(groups, lig_segments, rest)):
            name = f"LIG_{g}_{i + 1}"
            elsets[name] = np.array([n_hexes + i])
            table = spring_table(mats, g, seg, template.ligament_fibres(g), length)  # a bundle's fibre: its share
            sections.append(Section(elset=name, spring_force_elongation=table))
            lig_counts[g] = lig_counts.get(g, 0) + 1
    if fn is not None:
        first = n_hexes + len(lig_conn)
        blocks["FACETS"] = (fn.element_type, facet_conn)
        for i, (_, name) in enumerate(fn.sections):
            elsets[name] = np.array([first + i])
        sections += fn.section_list()
        lig_counts["FACET"] = len(joints)
        if facets.tip_clearance_mm is not None:
            lig_counts["FACET_TIP"] = len(joints)

    endplates, frames, rigid = {}, {}, {}
    arch_springs: list[tuple[str, np.ndarray]] = []
    for v in verts:
        if v == "S1":
            ep = np.arange(n2)
            frames[v] = fit_endplate(points[ep]).frame
            endplates[v] = new_of[ep]
            continue
        inf_l, sup_l = body_layer(template, v, 0.0), body_layer(template, v, 1.0)
        inf, sup = inf_l * n2 + np.arange(n2), sup_l * n2 + np.arange(n2)
        endplates[v] = new_of[np.concatenate([inf, sup])]
        frames[v] = vertebra_frame(template, points, v)[0]
        a = np.concatenate([new_of[anchors[v]], extra_tied[v]])
        if peds is not None and v in peds[0].ends:  # the arch hangs on its pedicles' end faces
            wall = ped_ids(peds[0].ends[v])
            tied = np.concatenate([ped_ids(peds[0].nodes_of[v]), a])
        else:
            wall = new_of[posterior_wall(template, v)]
            tied = np.concatenate([wall, a])
        # the loaded top and a unit's fixed bottom vertebra are potted in vitro: the whole vertebra (body
        # and arch) is rigid.  With only its superior endplate rigid, ccx's Newton iterations stalled next
        # to the rigid body once the top had turned > 13 deg (lumbar flexion, docs/explanation/fe-model.md).
        body = new_of[np.arange(inf_l * n2, (sup_l + 1) * n2)]
        if v == verts[-1]:
            fixed = np.unique(np.concatenate([tied, body]))
        elif v == top:
            rigid[v] = np.unique(np.concatenate([tied, body]))
        elif len(a):
            # an intermediate arch: a stiff truss from every anchor to every posterior-wall node and between
            # the anchors.  Seven *RIGID BODY arches in the lumbar model stalled ccx's Newton iterations
            # (flexion: 14 -> 43 iterations per increment, no convergence past 35 % of the load, discs
            # alone); without them, 10 per increment to the full load (docs/explanation/fe-model.md).
            # less than MIN_SPRING_MM long (the extension stop's node sits on the IAP-tip anchor): no direction
            pairs = drop_short(pts, truss_pairs(a, wall))
            arch_springs.append((v, pairs))
    if bottom == "S1":
        fixed = new_of[np.arange(n2)]
    if len(ties):  # a midside node on an edge of the fixed or the rigid vertebra joins that set (`ties_on`)
        on_fixed = ties_on(ties, fixed)
        fixed = np.concatenate([fixed, ties[on_fixed, 0]])
        on_rigid = ties_on(ties, rigid[top]) & ~on_fixed
        rigid[top] = np.concatenate([rigid[top], ties[on_rigid, 0]])
        ties = ties[~on_fixed & ~on_rigid]
    if arch_springs:
        first = sum(len(c) for _, c in blocks.values())
        blocks["ARCHES"] = ("SPRINGA", np.concatenate([p for _, p in arch_springs]))
        for v, p in arch_springs:
            elsets[f"ARCH_{v}"] = np.arange(first, first + len(p))
            sections.append(Section(elset=f"ARCH_{v}", spring_force_elongation=CONNECTOR_TABLE))
            first += len(p)
    if len(rib_conn):
        first = sum(len(c) for _, c in blocks.values())
        blocks["RIBS"] = ("SPRINGA", rib_conn)
        for i, (g, k) in enumerate(zip(rn.spring_groups, rn.stiffness)):
            elsets[f"{g}_{i + 1}"] = np.array([first + i])
            sections.append(Section(elset=f"{g}_{i + 1}", spring_force_elongation=linear_spring_table(k)))
        lig_counts["RIB_HEAD"] = len(rn.points)
    if peds is not None:
        add_block(blocks, elsets, sections, ped_ids(peds[0].hexes), peds[0].elsets)
    embedded = None
    if mats.fibre_springs:  # the annulus fibres, as in the exported decks (`spinecohort.fe.fibres`)
        fib = annulus_fibres(template, points, mats, hex_ids)
        pts, embedded = add_fibres(pts, blocks, elsets, sections, fib, new_of)
        source = np.concatenate([source, np.full(len(fib.points), -1)])
    fe = FEModel(
        nodes=pts,
        element_blocks=blocks,
        node_sets={},
        element_sets=elsets,
        materials=material_cards(mats, template),
        sections=sections,
        heading=heading or f"spinecohort ROM model {top}-{bottom}",
        orientations=[o for o in orientations.values() if o.name in used_orient],
        midside_ties=ties,
        embedded_ties=embedded,
    )
    # a partial CEP's rim fibres tie to the potted vertebrae's endplate layers: the tied nodes leave the rigid body
    # and the fixed set and hang on them by a 1 mm cortical plate, whatever the body's layer count
    # (`FEModel.embedded_hosts`, `potted_plate`)
    hosts = fe.embedded_hosts()
    carried = hosts
    plates = {top: (endplates[top][:n2], 1.0)}  # the top's inferior endplate layer, its bone above
    if bottom == "S1":
        if np.isin(fixed, hosts).any():
            # S1's plate is the L5-S1 disc's bottom node layer, without bone above or below: the whole plate is
            # carried (no change for a whole-layer CEP, whose fibres never reach it)
            if len(fixed) != n2:  # a quadratic element's midside node on the plate: fixed directly, not potted
                raise ValueError("the S1 plate carries midside nodes; it cannot be potted under a partial CEP")
            carried = np.union1d(hosts, fixed)
        plates[bottom] = (endplates[bottom], -1.0)
    else:
        plates[bottom] = (endplates[bottom][n2:], -1.0)  # the bottom's superior endplate layer, its bone below
    fe, new = potted_plate(
        fe, template.grid.quads, carried, {v: (plate, frames[v][:, 2], side) for v, (plate, side) in plates.items()}
    )
    rigid[top] = np.concatenate([rigid[top][~np.isin(rigid[top], carried)], new[top]])
    fixed = np.concatenate([fixed[~np.isin(fixed, carried)], new[bottom]])
    if bottom == "S1":  # the sacrum's ligament and facet nodes move with the fixed S1 (potted with the pelvis)
        fixed = np.concatenate([fixed, new_of[anchors["S1"]], extra_tied.get("S1", np.zeros(0, np.int64))])
    source = np.concatenate([source, np.full(len(fe.nodes) - len(source), -1)])
    return RomModel(fe, verts, endplates, rigid, fixed, frames, np.arange(n_hexes), source, lig_counts)


def check_elements(model: RomModel, min_scaled_jacobian: float = 0.0) -> float:
    """Refuse a model with an inverted (or too distorted) hex before the solver is called; returns the
    minimum scaled Jacobian."""
    from spinecohort.mesh.quality.verdict import scaled_jacobian

    hexes = np.concatenate([c[:, :8] for t, c in model.fe.element_blocks.values() if t in SOLID_TYPES])
    sj = scaled_jacobian(model.fe.nodes, hexes)
    bad = int((sj <= min_scaled_jacobian).sum())
    if bad:
        worst = int(np.argmin(sj))
        raise RomError(
            f"{bad} hex element(s) of the ROM model {model.top}-{model.vertebrae[-1]} have a scaled "
            f"Jacobian <= {min_scaled_jacobian} (min {sj.min():.3f} at element {worst + 1}): inverted "
            f"or degenerate; refusing to run the solver"
        )
    return float(sj.min())
