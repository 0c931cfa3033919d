"""From the hex template (+ any model's node coordinates) to an Abaqus/CalculiX deck, STL and VTU: `fe_model`
assembles one connected mechanical body (element blocks by type, sets, sections, connectors, facet joints, the
annulus fibre springs) with the materials of `spinecohort.fe.materials`; `write_deck` writes it after the
connectivity check.  The deck's contents: docs/reference/deck.md.  Units: mm, N, MPa.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spinecohort.fe.abaqus import FEModel, Orientation, Section
from spinecohort.fe.fibres import EmbeddedFibres, embedded_fibres
from spinecohort.fe.ligament_curves import ligament_segments
from spinecohort.fe.materials import (
    ANNULUS_GROUND,
    ANNULUS_MATERIAL,
    DEFAULT_MATERIALS,
    FEMaterials,
    annulus_material,
    annulus_ring_k1,
    annulus_ring_sets,
    material_cards,
    spring_table,
)
from spinecohort.fe.writers import write_inp, write_vtu
from spinecohort.mesh.template import RIM_TISSUE, HexTemplate

#: the annulus' element of every deck: ccx 2.20's ELASTIC_FIBER law aborts with C3D8/C3D8I, and now and then with
#: C3D20R (docs/explanation/fe-model.md "Elements")
DISC_HEX_TYPE = "C3D8R"
#: the nucleus' element: quadratic, tied to the annulus and endplates by midside *EQUATIONs
#: (`spinecohort.fe.quadratic`).
#: A C3D8R nucleus leaked moment (the T10-S1 base carried 87 % of 7.5 N.m), C3D8 locks it (docs/explanation/fe-model.md)
NUCLEUS_HEX_TYPE = "C3D20R"
#: hex sets (by name suffix) of the disc soft tissue, the elements after the bone's: the annulus (``disc_hex_type``)
#: and the nucleus (``nucleus_hex_type``, its own block when it differs; see `hex_blocks`)
DISC_TYPE_TISSUES: tuple[str, ...] = ("_AF", "_NP")


def disc_hexes(template: HexTemplate, tissues: tuple[str, ...] = DISC_TYPE_TISSUES) -> np.ndarray:
    """(E,) bool: the template's hexes of the disc soft tissue (`DISC_TYPE_TISSUES`; ``("_NP",)``: the nucleus)."""
    disc = np.zeros(len(template.hexes), bool)
    for name, idx in template.elsets.items():
        if template.elset_kind[name] == "hex" and name.endswith(tissues):
            disc[idx] = True
    return disc


def hex_blocks(
    template: HexTemplate,
    hex_ids: np.ndarray,
    hex_type: str,
    disc_hex_type: str | None,
    nucleus_hex_type: str | None = None,
) -> tuple[np.ndarray, dict[str, tuple[str, np.ndarray]]]:
    """Order the template hexes `hex_ids` into element blocks by element type: ``HEXES`` (bone, cartilage
    endplates: `hex_type`), ``HEXES_DISC`` (annulus, and the nucleus unless it differs: `disc_hex_type`,
    None = `hex_type`), ``HEXES_NP`` (the nucleus when `nucleus_hex_type` differs from the annulus'), each in
    template order.  Returns the reordered ids and {block: (type, (E, 8) template node indices)} in that order."""
    disc_hex_type = disc_hex_type or hex_type
    nucleus_hex_type = nucleus_hex_type or disc_hex_type
    hex_ids = np.asarray(hex_ids, dtype=np.int64)
    disc, nucleus = disc_hexes(template)[hex_ids], disc_hexes(template, ("_NP",))[hex_ids]
    kind = np.where(disc & (nucleus_hex_type != disc_hex_type) & nucleus, 2, np.where(disc, 1, 0))
    if disc_hex_type == hex_type:
        kind[kind == 1] = 0
    order = hex_ids[np.argsort(kind, kind="stable")]
    names = {0: ("HEXES", hex_type), 1: ("HEXES_DISC", disc_hex_type), 2: ("HEXES_NP", nucleus_hex_type)}
    bounds = np.concatenate([[0], np.cumsum(np.bincount(kind, minlength=3))])
    blocks = {
        names[k][0]: (names[k][1], template.hexes[order[bounds[k] : bounds[k + 1]]])
        for k in range(3)
        if bounds[k + 1] > bounds[k]
    }
    return order, blocks


#: node sets by which an exported deck is fixed, in order of preference
FIXED_SETS = ("PELVIS", "EP_SUP_S1")


def disc_orientations(template: HexTemplate, points: np.ndarray) -> dict[str, Orientation]:
    """Cylindrical fibre system per disc ('D_L4L5' -> OR_D_L4L5): axis from the centre of the disc's lower
    bounding node layer to the centre of its upper one (mm)."""
    from spinecohort.mesh.template import disc_runs

    n2 = len(template.grid.nodes)
    out = {}
    for first, end in disc_runs(template.layers):
        name = "D_" + template.layers[first]["disc"].replace("-", "")
        lo = points[(first - 1) * n2 : first * n2].mean(0)
        hi = points[end * n2 : (end + 1) * n2].mean(0)
        out[name] = Orientation(f"OR_{name}", tuple(map(float, lo)), tuple(map(float, hi)))
    return out


def hex_section(name: str, orientations: dict[str, Orientation] | None) -> Section:
    """Section of a template hex set (V_<lvl>_CORE/SHELL, D_<disc>_NP/AF/CEP/RIM) or of an annulus ring's set
    (D_<disc>_AF_R<k>, `annulus_ring_sets`: material ELASTIC_FIBER_AF_R<k>, the disc's orientation).
    orientations None: spring fibres, the annulus is its isotropic ground substance (material AF)."""
    parts = name.split("_")
    tissue = parts[-1]
    if orientations is not None:  # ccx's fibre law: the annulus material carries the fibres in the disc's system
        if parts[0] == "D" and len(parts) == 4 and parts[2] == "AF" and parts[3].startswith("R"):
            ring = int(parts[3][1:])
            orient = orientations["_".join(parts[:2])].name
            return Section(elset=name, material=annulus_material(ring), orientation=orient)
        if tissue == "AF":
            return Section(elset=name, material=ANNULUS_MATERIAL, orientation=orientations[name[:-3]].name)
    # AF with spring fibres: its ground substance, material ANNULUS_GROUND ("AF")
    material = {"CORE": "CANCELLOUS", "SHELL": "CORTICAL", RIM_TISSUE: ANNULUS_GROUND}.get(tissue, tissue)
    return Section(elset=name, material=material)


def annulus_fibres(
    template: HexTemplate, points: np.ndarray, mats: FEMaterials, hex_ids: np.ndarray | None = None
) -> EmbeddedFibres:
    """The fibre springs (`spinecohort.fe.fibres`) of the template's annulus hexes (only those in `hex_ids`, if
    given) at `points` (template node order, mm): each disc's cylindrical axis sets the directions, k1 per ring
    (`annulus_ring_k1`) or uniform.  Hosts are template node ids."""
    orient = disc_orientations(template, points)
    ring_k1 = annulus_ring_k1(template, mats)
    ring_of_hex = template.grid.quad_ring[np.arange(len(template.hexes)) % len(template.grid.quads)]
    ids, axis_a, axis_b = [], [], []
    for name, idx in template.elsets.items():
        # the annulus and its insertion into the bony rim (a partial CEP's D_<disc>_RIM): the fibres reach the bone
        if template.elset_kind[name] != "hex" or not name.endswith(("_AF", "_" + RIM_TISSUE)):
            continue
        if hex_ids is not None:
            idx = idx[np.isin(idx, hex_ids)]
        o = orient[name.rsplit("_", 1)[0]]
        ids.append(idx)
        axis_a.append(np.broadcast_to(o.axis_a_mm, (len(idx), 3)))
        axis_b.append(np.broadcast_to(o.axis_b_mm, (len(idx), 3)))
    ids = np.concatenate(ids)
    k1_of_ring = np.full(template.grid.shell_ring + 1, mats.fibre_k1_mpa)
    k1_of_ring[list(ring_k1)] = list(ring_k1.values())  # {} (uniform k1): unchanged
    k1 = k1_of_ring[ring_of_hex[ids]]
    return embedded_fibres(
        points,
        template.hexes[ids],
        np.concatenate(axis_a),
        np.concatenate(axis_b),
        k1,
        mats.fibre_k2,
        mats.fibre_angle_deg,
        hex_ids=ids,
        per_hex=mats.fibre_springs_per_hex,
    )


def add_fibres(
    pts: np.ndarray,
    blocks: dict,
    elsets: dict,
    sections: list,
    fibres: EmbeddedFibres,
    node_of: np.ndarray | None = None,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Append the fibre springs to a model being built: their end nodes after `pts`, a last SPRINGA block
    ``FIBRES`` with one element set and table per force bin (``FIB_<k>``).  node_of: template node id -> model
    node index (a submodel's renumbering; None: the same).  Returns the points and the ends' embedded ties."""
    n = len(pts)
    hosts = fibres.hosts if node_of is None else node_of[fibres.hosts]
    if (hosts < 0).any():
        raise ValueError("an annulus fibre's host hex has a node outside the model")
    first = sum(len(c) for _, c in blocks.values())
    blocks["FIBRES"] = ("SPRINGA", n + fibres.springs)
    for g, table in enumerate(fibres.tables):
        elsets[f"FIB_{g + 1}"] = first + np.flatnonzero(fibres.group == g)
        sections.append(Section(elset=f"FIB_{g + 1}", spring_force_elongation=table))
    ties = (np.column_stack([n + np.arange(len(fibres.points)), hosts]), fibres.weights)
    return np.concatenate([pts, fibres.points]), ties


def fe_model(
    template: HexTemplate,
    points: np.ndarray | None = None,
    hex_type: str = "C3D8",
    include_all: bool | None = None,
    heading: str = "spinecohort model",
    materials: FEMaterials | None = None,
    disc_hex_type: str | None = DISC_HEX_TYPE,
    connectors: bool = True,
    nucleus_hex_type: str | None = NUCLEUS_HEX_TYPE,
) -> FEModel:
    """The template as an FEModel with the given node coordinates (default: the template's own): one
    connected mechanical body (`spinecohort.fe.connections`).

    Element blocks, in this order: ``HEXES`` (bone, cartilage endplates: `hex_type`), ``HEXES_DISC`` (annulus:
    `disc_hex_type`, C3D8R; ccx 2.20's fibre law aborts with C3D8/C3D8I), ``HEXES_NP`` (nucleus:
    `nucleus_hex_type`, C3D20R with its midside nodes tied to its neighbours, `FEModel.midside_ties`; C3D8R leaks
    moment, C3D8 locks), ``SURFACES`` (S3 skins), ``LIGAMENTS`` (tension-only SPRINGA), ``CONNECTORS`` (linear
    SPRINGA, element sets ``CONN_*``; ``CONN_FACET_<lvl>`` hang the facet nodes on their vertebra), ``FACETS``
    (facet-joint contact struts, SPRINGA, `spinecohort.fe.facets`; element sets ``FACET_*``), ``FIBRES`` (the
    annulus fibre springs, `spinecohort.fe.fibres`; element sets ``FIB_*``; none with
    ``fibre_model="elastic_fiber"``).  Nodes: the template's (ids 1..N, template order), then the facet nodes
    (materials.facets None: none), then the quadratic hexes' midside nodes, then the fibre springs' end nodes.
    Hex elements are therefore numbered bone and endplates first, then annulus, then nucleus, each in template
    order.  Node sets: the template's plus ``PELVIS`` (where a user fixes the model).  disc_hex_type None: the
    disc in ``HEXES`` (template order); connectors False: no ``CONNECTORS``
    (a deck of loose parts, for pictures only).
    materials: default `DEFAULT_MATERIALS` (= config/config.yaml); include_all overrides its switch.
    """
    from spinecohort.fe.connections import CONNECTOR_TABLE, base_nodes, model_connectors, truss_pairs
    from spinecohort.fe.facets import facet_nodes, facet_pairs
    from spinecohort.fe.pedicles import add_block, model_pedicles
    from spinecohort.fe.quadratic import quadratic_blocks

    mats = DEFAULT_MATERIALS if materials is None else materials
    include_all = mats.include_all if include_all is None else include_all
    pts = template.nodes if points is None else np.asarray(points, dtype=np.float64)
    if pts.shape != template.nodes.shape:
        raise ValueError(f"points have shape {pts.shape}, the template has {template.nodes.shape}")
    template_points = pts
    lig_keep = np.ones(len(template.ligaments), bool)
    if not include_all:
        lig_keep[template.elsets["LIG_ALL"]] = False
    hex_order, blocks = hex_blocks(template, np.arange(len(template.hexes)), hex_type, disc_hex_type, nucleus_hex_type)
    pos_of_hex = np.empty(len(template.hexes), dtype=np.int64)
    pos_of_hex[hex_order] = np.arange(len(hex_order))
    blocks["SURFACES"] = ("S3", template.tris)
    blocks["LIGAMENTS"] = ("SPRINGA", template.ligaments[lig_keep])
    offset = {"hex": 0, "tri": len(template.hexes), "lig": len(template.hexes) + len(template.tris)}
    lig_new = np.cumsum(lig_keep) - 1
    lig_segments = ligament_segments(template)
    elsets = {}
    ring_sets = annulus_ring_sets(template, mats)  # {} unless k1 is graded
    for name, idx in template.elsets.items():
        kind = template.elset_kind[name]
        if kind == "lig":
            idx = lig_new[idx[lig_keep[idx]]]
            if len(idx) == 0:
                continue
        elif kind == "hex":
            if name in ring_sets:
                for ring_name, ring_idx in ring_sets[name].items():
                    elsets[ring_name] = offset["hex"] + np.sort(pos_of_hex[ring_idx])
                continue
            idx = np.sort(pos_of_hex[idx])
        elsets[name] = offset[kind] + np.asarray(idx)
    fn = None
    if connectors and mats.facets is not None and "LIG_CL" in template.elsets:
        fn = facet_nodes(template, pts, facet_pairs(template), mats.facets)
    # the pedicles' nodes after the facet nodes; each arch hangs on its pedicles' end faces (`fe.pedicles`)
    n_first_ped = len(pts) + (len(fn.points) if fn is not None else 0)
    peds = model_pedicles(template, pts, mats.pedicle_layers, n_first_ped)
    bases, base_points = {}, template.nodes
    if peds is not None:
        bases = peds[0].ends
        base_points = np.zeros((n_first_ped + len(peds[1].points), 3))
        base_points[: len(pts)], base_points[n_first_ped:] = template.nodes, peds[1].points
    conn_sets = model_connectors(template, base_points, bases) if connectors else {}
    if fn is not None:
        # facet joints: new nodes after the template's (ids N+1..), each hung with its arch (its pedicles' ends, else
        # its posterior wall; S1's: the S1 plate) by the arch truss (coordinate-free: the same springs in every model)
        n = len(pts)
        for v, ix in fn.tied.items():
            conn_sets[f"CONN_FACET_{v}"] = truss_pairs(n + ix, bases.get(v, base_nodes(template, v)))
    if conn_sets:
        first = offset["lig"] + int(lig_keep.sum())
        blocks["CONNECTORS"] = ("SPRINGA", np.concatenate(list(conn_sets.values())))
        for name, pairs in conn_sets.items():
            elsets[name] = np.arange(first, first + len(pairs))
            first += len(pairs)
    if fn is not None:
        first = sum(len(c) for _, c in blocks.values())
        blocks["FACETS"] = (fn.element_type, len(pts) + fn.gaps)
        for i, (_, name) in enumerate(fn.sections):
            elsets[name] = np.array([first + i])
    orientations = disc_orientations(template, pts)
    hex_orient = None if mats.fibre_springs else orientations
    sections = []
    for name, kind in template.elset_kind.items():
        if name in ring_sets:
            sections += [hex_section(ring_name, orientations) for ring_name in ring_sets[name]]
            continue
        if name not in elsets:
            continue
        if kind == "hex":
            sections.append(hex_section(name, hex_orient))
        elif kind == "tri":
            sections.append(Section(elset=name, material="CORTICAL", thickness_mm=mats.shell_thickness_mm))
        else:
            # one table per group and segment, at the segment's mean rest length; LIG_<group> stays their union
            group, ids = name.split("_", 1)[1], template.elsets[name]
            ids = ids[lig_keep[ids]]
            segs = lig_segments[ids]
            for seg in dict.fromkeys(segs):
                sub = ids[segs == seg]
                ends = pts[template.ligaments[sub]]
                rest = float(np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1).mean())
                sub_name = f"{name}_{seg.replace('-', '')}"
                elsets[sub_name] = offset["lig"] + lig_new[sub]
                table = spring_table(mats, group, seg, template.ligament_fibres(group), rest)  # a bundle's fibre
                sections.append(Section(elset=sub_name, spring_force_elongation=table))
    sections += [Section(elset=name, spring_force_elongation=CONNECTOR_TABLE) for name in conn_sets]
    if fn is not None:
        sections += fn.section_list()
        pts = np.concatenate([pts, fn.points])
    if peds is not None:
        add_block(blocks, elsets, sections, peds[0].hexes, peds[0].elsets)
        pts = np.concatenate([pts, peds[0].points])
    # quadratic hexes' midside nodes after every other node, tied to their linear neighbours (`fe.quadratic`)
    pts, blocks, ties = quadratic_blocks(pts, blocks)
    embedded = None
    if mats.fibre_springs:  # the annulus fibres, last nodes and last elements (`spinecohort.fe.fibres`)
        pts, embedded = add_fibres(pts, blocks, elsets, sections, annulus_fibres(template, template_points, mats))
    node_sets = dict(template.nsets)
    if "PELVIS" in template.elsets and "PELVIS" not in node_sets:
        node_sets["PELVIS"] = np.unique(template.tris[template.elsets["PELVIS"]])
    return FEModel(
        nodes=pts,
        element_blocks=blocks,
        node_sets=node_sets,
        element_sets=elsets,
        materials=material_cards(mats, template),
        sections=sections,
        heading=heading,
        orientations=[] if mats.fibre_springs else list(orientations.values()),
        midside_ties=ties,
        embedded_ties=embedded,
    )


#: element blocks a picture of a deck leaves out (`write_vtu`'s leave_out): connector and facet-strut lines
NOT_ANATOMY = ("CONNECTORS", "FACETS")


def fixed_set(model: FEModel) -> str:
    """The node set a user fixes the exported deck by: ``PELVIS`` (else the S1 plate ``EP_SUP_S1``)."""
    for name in FIXED_SETS:
        if name in model.node_sets:
            return name
    raise ValueError(f"the model has none of the node sets {FIXED_SETS} to fix it by")


def write_deck(model: FEModel, path: str | Path, provenance: str = "") -> Path:
    """Write an exported deck after checking that it is one body: every element reachable from the fixed
    set (`fixed_set`) through load-carrying elements (`spinecohort.fe.connectivity`); raises
    ConnectivityError naming the deck and its loose parts otherwise."""
    check_deck(model, str(path))
    return write_inp(model, path, provenance=provenance)


def check_deck(model: FEModel, deck: str) -> None:
    """The connectivity check of every exported deck (see `write_deck`); deck: its name for the message."""
    from spinecohort.fe.connectivity import check_connected

    check_connected(model, model.node_sets[fixed_set(model)], deck)


def read_deck_points(deck: str | Path, template: HexTemplate) -> np.ndarray:
    """The template-node coordinates (n_nodes, 3) mm of an exported deck: its first N nodes, ids 1..N (the
    facet-joint nodes after them derive from these); ValueError naming the deck if it is not an export."""
    from spinecohort.fe.inp_template import read_inp_nodes

    ids, points = read_inp_nodes(deck)
    n = template.n_nodes
    if len(points) < n or not np.array_equal(ids[:n], np.arange(1, n + 1)):
        raise ValueError(
            f"{deck}: {len(points)} nodes with ids {ids[:3]}..., but the template has {n} nodes numbered 1..N "
            f"first: not an exported spinecohort deck of this template"
        )
    return points[:n]


def write_model_files(
    template: HexTemplate,
    points: np.ndarray,
    out: str | Path,
    fmt: str,
    heading: str = "spinecohort model",
    materials: FEMaterials | None = None,
) -> Path:
    """Write one model as ``inp`` (Abaqus/CalculiX deck) or ``vtu``."""
    model = fe_model(template, points, heading=heading, materials=materials)
    if fmt == "inp":
        return write_deck(model, out, provenance=heading)
    if fmt == "vtu":
        return write_vtu(model, out)
    raise ValueError(f"unknown FE format '{fmt}' (inp | vtu)")
