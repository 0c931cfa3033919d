"""A pure-moment load step for a CalculiX deck, and the runnable load deck of a whole exported model.

The step: a REF and a ROT NODE per rigid body, the fixation, one static (NLGEOM) step with the moment on the
ROT NODE's DOF 1-3 (a moment on the REF NODE's DOF 4-6 without a ROT NODE is silently ignored by ccx 2.20),
the convergence controls the ROM analyses converge with, and node prints of the ROT NODE, of chosen node sets
and of the fixed nodes' reaction forces.  The ROM sub-model decks (`spinecohort.rom.deck`) and
``spinecohort export --load`` (`model_load_text`) write the same step.  Units: mm, N, N.mm (radians only
inside the deck).
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.fe.abaqus import FEModel, without_elements
from spinecohort.fe.connections import body_layer
from spinecohort.fe.export import fixed_set
from spinecohort.fe.facets import vertebra_frame
from spinecohort.fe.potting import potted_plate
from spinecohort.fe.writers import format_id_list, model_to_inp_text
from spinecohort.mesh.template import HexTemplate

#: load case -> (anatomical axis 0 lateral(+right) / 1 anterior / 2 cranial, sign of the moment vector).
#: RAS frame: flexion tilts the top anteriorly = negative rotation about +x; right lateral bending tilts
#: it to +x = positive rotation about +y; left axial rotation turns the anterior side to the left
#: (-x) = positive rotation about +z.
LOAD_CASES: dict[str, tuple[int, int]] = {
    "flexion": (0, -1),
    "extension": (0, 1),
    "lateral_left": (1, -1),
    "lateral_right": (1, 1),
    "axial_left": (2, 1),
    "axial_right": (2, -1),
}


#: step controls of a whole-model load deck: the ROM's (config/config.yaml's rom block: field controls with a
#: 500 N reference force), smaller increments and `MODEL_TIME_INCREMENTATION`.  A whole spine turns ~17 times as
#: much as one unit and is softest at the start (slack ligaments and fibres): a first increment of 100 N.mm
#: diverges, 25 N.mm (`MODEL_INCREMENT_NMM`) converges in ~7 Newton iterations; later increments grow as ccx's
#: increment control allows, up to 5 % of the load (docs/explanation/fe-model.md "Loading the whole model")
MODEL_STEP_DEFAULTS = dict(
    nlgeom=True,
    min_increment=1e-5,
    max_increment=0.05,
    max_increments=1000,
    average_force_n=500.0,
)
MODEL_INCREMENT_NMM = 25.0
#: the whole model's increment control: as the ROM's, but an increment grows (x1.5) after two that converged in
#: at most I_G = 16 iterations, and shrinks after one that took more than I_L = 20 (ccx's defaults 4 and 10).  The
#: whole spine's increments take 6-12 iterations, more for larger ones but fewer per newton-millimetre (0.05 %
#: of the load per iteration at 25 N.mm, 0.09 % at 84 N.mm on the test model): with I_G = 4 the step never left
#: its 25 N.mm first increment (300 increments for the load), with I_G = 8 it stayed at 84 N.mm.  The divergence
#: check starts at I_0 = 20, not ccx's 4, for the increments whose iterations cycle before they converge
#: (docs/explanation/fe-model.md "Elements")
MODEL_TIME_INCREMENTATION = "20, 30, 9, 200, 20, 16, , 20"


#: ccx's time-incrementation controls I_0, I_R, I_P, I_C, I_L, I_G, I_S, I_A of the ROM decks: more Newton iterations
#: before a cutback (I_C 16 -> 200) and more cutbacks (I_A 5 -> 20) than ccx's defaults (see `pure_moment_text`)
ROM_TIME_INCREMENTATION = "20, 30, 9, 200, 10, 4, , 20"


def arch_skin_free(fe: FEModel) -> FEModel:
    """The whole model as its load deck solves it: without the S3 skins of the posterior arches (element sets
    ``POST_<lvl>``).  Each arch acts through its truss of stiff connectors (ligament and facet anchors to the
    body's posterior wall, `spinecohort.fe.connections`), the arch the ROM sub-models carry and validate; the thin
    skins between the anchors carry nothing of the load, but under NLGEOM they made ccx's Newton iterations cycle
    (docs/explanation/fe-model.md "Loading the whole model").  The skin nodes stay in the deck."""
    arch = [np.asarray(idx) for name, idx in fe.element_sets.items() if name.startswith("POST_")]
    return without_elements(fe, np.unique(np.concatenate(arch)) if arch else np.zeros(0, np.int64))


def fully_integrated_nucleus(fe: FEModel) -> FEModel:
    """The whole model as its load deck solves it: the nucleus' reduced-integration C3D20R hexes as fully
    integrated C3D20 (same nodes, same ties).  At the whole spine's load the nucleus pressure of a thin thoracic
    disc made a spurious mode of C3D20R (zero strain at its 8 points) buckle: the all -3 SD model's right lateral
    bending stopped at 81 % of the load, its Newton corrections largest on the T4-T5 nucleus' inner nodes.
    C3D20 has no such mode; it is stiffer in bending (docs/explanation/fe-model.md "Loading the whole model")."""
    blocks = {name: ("C3D20" if t == "C3D20R" else t, conn) for name, (t, conn) in fe.element_blocks.items()}
    return dataclasses.replace(fe, element_blocks=blocks)


def guide_equations(moment_nmm: np.ndarray) -> tuple[int, list[tuple[int, float]], float]:
    """How a guided top turns about the moment's axis a = m / |m| only: its ROT NODE's rotation vector theta
    stays along a, i.e. theta_h = (a_h / a_l) theta_l for the two components h other than l, the global axis
    the moment has most of (the loaded one).
    Returns (l, [(h, -a_h / a_l), ...] the coefficients of theta_l in the equations theta_h - ... = 0, the
    generalised force on theta_l (N.mm) that does the work of m: m . dtheta = (m . a / a_l) dtheta_l =
    |m|^2 / m_l).  About an axis at any angle to the global ones (a rotation about a fixed axis is conjugate to
    the moment about it, so no large-rotation correction is needed)."""
    m = np.asarray(moment_nmm, dtype=np.float64)
    if not np.all(np.isfinite(m)) or not np.linalg.norm(m) > 0:
        raise ValueError(f"a guided top needs a finite, non-zero moment, got {m}")
    loaded = int(np.argmax(np.abs(m)))
    held = [(h, float(-m[h] / m[loaded])) for h in range(3) if h != loaded]
    return loaded, held, float(m @ m / m[loaded])


def pure_moment_text(
    nodes_mm: np.ndarray,
    rigid_nodes: dict[str, np.ndarray],
    top: str,
    fixed_nodes: np.ndarray,
    print_sets: dict[str, np.ndarray],
    moment_nmm: np.ndarray,
    nlgeom: bool = True,
    initial_increment: float = 0.1,
    min_increment: float = 1e-4,
    max_increment: float = 0.25,
    max_increments: int = 100,
    average_force_n: float | None = None,
    correction_tolerance: float = 0.01,
    guided: bool = False,
    time_incrementation: str = ROM_TIME_INCREMENTATION,
    reaction_set: str = "FIXED",
) -> str:
    """What follows a deck's model data for one pure-moment load case: a REF and a ROT NODE per rigid body
    (numbered right after the mesh), the *RIGID BODY of each (0-based node indices), the fixed nodes
    (U1-U3 = 0), one static step with the moment vector `moment_nmm` (3,) N.mm on the ROT NODE of `top`,
    and node prints (U) of that ROT NODE (set ROTTOP: its U1-U3 are the rotations in rad) and of each
    print set, and the forces (RF) of `reaction_set`: the fixed nodes' reactions (`spinecohort.rom.reaction` reads
    them), or a rigid body's set ``RB_<top>`` (U and RF: the moment its nodes pass to the spine).  The step
    controls are the ones the ROM analyses converge with (docs/explanation/fe-model.md).

    guided: the ROT NODE's rotation vector is tied to the moment's axis by two *EQUATIONs and the moment acts
    on its remaining component (`guide_equations`): the top turns about the load's axis only, at any angle to
    the global axes; the moment that guides it is what the fixed base carries beyond the load
    (`spinecohort.rom.run`).  Where the free top stops at an out-of-plane bifurcation
    (docs/explanation/fe-model.md) this reaches the load; before it, the path is the free one (T10-S1 flexion:
    5,862.0 against 5,861.3 N.mm at 29.48 deg)."""
    n = len(nodes_mm)
    parts = []
    extra, rb, next_id = [], [], n + 1
    rot_top = None
    for v, nodes in rigid_nodes.items():
        c = nodes_mm[nodes].mean(0)
        ref, rot = next_id, next_id + 1
        next_id += 2
        extra += [f"{ref}, {c[0]:.6f}, {c[1]:.6f}, {c[2]:.6f}\n", f"{rot}, {c[0]:.6f}, {c[1]:.6f}, {c[2]:.6f}\n"]
        rb.append((v, ref, rot, nodes))
        if v == top:
            rot_top = rot
    if rot_top is None:
        raise ValueError(f"the top vertebra {top} has no rigid body to load")
    # extra nodes right after the mesh: ccx allocates memory by the largest node id
    parts.append("*NODE, NSET=RBNODES\n" + "".join(extra))
    for v, ref, rot, nodes in rb:
        parts.append(f"*NSET, NSET=RB_{v}\n" + format_id_list(nodes + 1))
        parts.append(f"*RIGID BODY, NSET=RB_{v}, REF NODE={ref}, ROT NODE={rot}\n")
    parts.append("*NSET, NSET=FIXED\n" + format_id_list(np.unique(fixed_nodes) + 1))
    for name, ids in print_sets.items():
        parts.append(f"*NSET, NSET={name}\n" + format_id_list(np.asarray(ids) + 1))
    parts.append(f"*NSET, NSET=ROTTOP\n{rot_top}\n")
    parts.append("*BOUNDARY\nFIXED, 1, 3\n")
    m = np.asarray(moment_nmm, dtype=np.float64)
    if guided:
        # the rotation vector stays along the moment's axis (`guide_equations`); a component the axis has
        # none of is held by a boundary condition (ccx needs a non-zero coefficient per equation term); ccx
        # reads a number of at most 20 characters, so 12 significant digits
        loaded, held, load_l = guide_equations(m)
        tied = [(h, c) for h, c in held if abs(c) > 1e-12]
        fixed = [h for h, c in held if abs(c) <= 1e-12]
        if tied:
            parts.append(
                "*EQUATION\n"
                + "".join(f"2\n{rot_top}, {h + 1}, 1.0, {rot_top}, {loaded + 1}, {c:.12g}\n" for h, c in tied)
            )
        if fixed:
            parts.append("*BOUNDARY\n" + "".join(f"{rot_top}, {h + 1}, {h + 1}, 0.0\n" for h in fixed))
        cload = {loaded: load_l}
    else:
        cload = dict(enumerate(m))
    step = f"*STEP, NLGEOM, INC={max_increments}\n" if nlgeom else "*STEP\n"
    parts.append(step + "*STATIC\n")
    if nlgeom:
        parts.append(f"{initial_increment}, 1.0, {min_increment}, {max_increment}\n")
    if nlgeom:
        # more Newton iterations before a cutback (IC 16 -> 200) and more cutbacks (IA 5 -> 20) than ccx's
        # defaults: with tension-only springs and the exponential fibre law both switching on, the default
        # controls stalled the test model's L3-L4 extension at 47 % of the load; these converge
        # (docs/explanation/fe-model.md)
        parts.append(f"*CONTROLS, PARAMETERS=TIME INCREMENTATION\n{time_incrementation}\n")
        if average_force_n:
            # ccx accepts an iteration when the largest residual is < 0.5 % of the model's average nodal
            # force.  Under a pure moment that average is ~0.3 N (soft tissue, few loaded nodes), so the
            # criterion asked for 0.002 N on rigid-body resultants and stalled the lumbar runs for dozens
            # of iterations per increment; a user-defined reference force fixes the scale
            # (docs/explanation/fe-model.md).
            # correction_tolerance: ccx's C_n (largest displacement correction / largest increment); the
            # run_case's relaxed attempt raises it, the residual criterion stays
            parts.append(
                f"*CONTROLS, PARAMETERS=FIELD\n0.005, {correction_tolerance!r}, 0.01, {average_force_n!r}, "
                "0.02, 1e-5, 1e-3, 1e-8\n"
            )
    parts.append("*CLOAD\n" + "".join(f"{rot_top}, {k + 1}, {v:.6f}\n" for k, v in cload.items()))
    parts.append("*NODE PRINT, NSET=ROTTOP\nU\n" + "".join(f"*NODE PRINT, NSET={name}\nU\n" for name in print_sets))
    # the fixed nodes' reactions: the moment the fixation carries (`spinecohort.rom.reaction`); a moving set's
    # forces need its displacements for their lever arms
    if reaction_set == "FIXED":
        parts.append("*NODE PRINT, NSET=FIXED\nRF\n")
    else:
        parts.append(f"*NODE PRINT, NSET={reaction_set}\nU\n*NODE PRINT, NSET={reaction_set}\nRF\n")
    parts.append("*END STEP\n")
    return "".join(parts)


def model_load_text(
    fe: FEModel,
    template: HexTemplate,
    case: str,
    top: str = "T1",
    moment_nmm: float = 7500.0,
    node_file: bool = True,
    guided: bool = False,
    **step_kw,
) -> str:
    """A complete, runnable pure-moment deck of a whole exported model (`spinecohort.fe.export.fe_model`, nodes in
    template order): the model data without the arches' skins (`arch_skin_free`: each arch acts through its
    connector truss) and with a fully integrated nucleus (`fully_integrated_nucleus`), the pelvis fixed (node set
    ``PELVIS``, else the S1 plate), the body of vertebra `top` rigid (its hex nodes; its arch hangs on it by the
    connectors: a rigid body holding shell nodes slowed ccx's Newton iterations to a stall) and loaded with
    `moment_nmm` (N.mm) about its anatomical axis of `case`, one NLGEOM step with the ROM's convergence controls
    (`step_kw`: those of `pure_moment_text`; default `MODEL_STEP_DEFAULTS`, first increment 25 N.mm, increments
    growing by `MODEL_TIME_INCREMENTATION`), ROT NODE rotations (rad) and the top's rigid nodes' U and RF
    (`spinecohort.rom.reaction.moment_on_top`) printed to the .dat file and, if node_file, displacements to the .frd
    file; the load's axis in a comment (`load_axis`).
    guided: the top turns about the load's axis only (two *EQUATIONs on its ROT NODE, `guide_equations`), as the
    ROM's lumbar model: free, the whole spine's extension needs 17-18 Newton iterations an increment and stalls.
    Solve with ``ccx -i <job>``."""
    if case not in LOAD_CASES:
        raise ValueError(f"unknown load case '{case}' (one of {list(LOAD_CASES)})")
    if top not in LEVELS:
        raise ValueError(f"top vertebra '{top}' is not one of {LEVELS}")
    if len(fe.nodes) < template.n_nodes:  # the template's nodes first, then the facet-joint nodes
        raise ValueError(f"the deck has {len(fe.nodes)} nodes, the template {template.n_nodes}: not its export")
    fe = fully_integrated_nucleus(arch_skin_free(fe))
    n2 = len(template.grid.nodes)
    inf, sup = body_layer(template, top, 0.0), body_layer(template, top, 1.0)
    rigid = np.arange(inf * n2, (sup + 1) * n2)
    if fe.midside_ties is not None and len(fe.midside_ties):
        # a midside node on an edge of the rigid vertebra joins the rigid body (`spinecohort.fe.quadratic.ties_on`)
        from spinecohort.fe.quadratic import ties_on

        on_rigid = ties_on(fe.midside_ties, rigid)
        rigid = np.concatenate([rigid, fe.midside_ties[on_rigid, 0]])
        fe = dataclasses.replace(fe, midside_ties=fe.midside_ties[~on_rigid])
    # a partial CEP's rim fibres tie to deformable nodes, held by a 1 mm cortical plate on the inferior endplate layer
    frame = vertebra_frame(template, fe.nodes, top)[0]
    hosts = fe.embedded_hosts()
    fe, new = potted_plate(fe, template.grid.quads, hosts, {top: (inf * n2 + np.arange(n2), frame[:, 2], 1.0)})
    rigid = np.concatenate([rigid[~np.isin(rigid, hosts)], new[top]])
    axis, sign = LOAD_CASES[case]
    a = sign * frame[:, axis]  # the load's axis (global unit vector)
    first = min(MODEL_INCREMENT_NMM / moment_nmm, MODEL_STEP_DEFAULTS["max_increment"])
    kw = {
        **MODEL_STEP_DEFAULTS,
        "initial_increment": first,
        "time_incrementation": MODEL_TIME_INCREMENTATION,
        **step_kw,
    }
    text = pure_moment_text(
        fe.nodes,
        {top: rigid},
        top,
        fe.node_sets[fixed_set(fe)],
        {},
        moment_nmm * a,
        guided=guided,
        # the pelvis's nodes are shell nodes, whose reactions ccx prints as zero (it keeps them on the shells'
        # expanded nodes): the top's rigid nodes tell the moment instead (`moment_on_top`)
        reaction_set=f"RB_{top}",
        **kw,
    )
    if node_file:
        text = text.replace("*END STEP\n", "*NODE FILE\nU\n*END STEP\n")
    how = ", turning about the load's axis only" if guided else ""
    # every comment line within ccx's 132 characters; the load's axis in words a reader and `load_axis` find: a
    # guided deck's *CLOAD is a generalised force on one rotation component, not the moment vector
    head = (
        f"** pure moment {case}: {moment_nmm / 1000:g} N.m on {top} (rigid body RB_{top}, moment on its ROT NODE"
        f"{how}),\n** {fixed_set(fe)} fixed; solve: ccx -i <job>\n"
        "** as the model deck without the arches' S3 skins, and the nucleus fully integrated (C3D20, not C3D20R)\n"
        "** ROTTOP's U1-U3 in the .dat: the top's rotation vector (rad, global x, y, z)\n"
        f"** load axis (global unit vector): {a[0]:.9f}, {a[1]:.9f}, {a[2]:.9f}\n"
        f"** RB_{top}'s RF in the .dat: the forces its nodes pass to the spine; their moment (lever arms to the\n"
        "** deformed nodes: U printed beside) is the load plus, guided, what holds the top on the axis\n"
    )
    return model_to_inp_text(fe, provenance=f"load case {case}") + head + text


def load_axis(deck_text: str) -> np.ndarray:
    """The load's axis (global unit vector) that `model_load_text` writes in a load deck's comment."""
    m = re.search(r"^\*\* load axis \(global unit vector\): ([^,\n]+), ([^,\n]+), ([^,\n]+)$", deck_text, re.MULTILINE)
    if m is None:
        raise ValueError("no '** load axis' line: not a load deck written by `spinecohort export --load`")
    return np.array([float(g) for g in m.groups()])
