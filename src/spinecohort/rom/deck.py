"""The complete CalculiX deck of one pure-moment load case of a ROM sub-model: model data, the rigid top
vertebra with its REF and ROT NODE, the fixation, one static (NLGEOM) step with the moment on the ROT NODE's
DOF 1-3 (a moment on the REF NODE's DOF 4-6 without a ROT NODE is silently ignored by ccx 2.20), and node
prints of every endplate node and of the ROT NODE.  Units: mm, N, N.mm (radians only inside the deck)."""

from __future__ import annotations

import numpy as np

from spinecohort.fe.abaqus import model_to_inp_text
from spinecohort.rom.submodel import RomError, RomModel

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
#: motion planes: the two load cases whose one-side ROMs add up to the full range of motion
PLANES = {
    "flexion_extension": ("flexion", "extension"),
    "lateral_bending": ("lateral_left", "lateral_right"),
    "axial_rotation": ("axial_left", "axial_right"),
}


def load_vector_nmm(model: RomModel, case: str, moment_nmm: float) -> np.ndarray:
    """Global moment vector (N.mm) of a load case, about the top vertebra's anatomical axis."""
    axis, sign = LOAD_CASES[case]
    return sign * moment_nmm * model.frames[model.top][:, axis]


def rom_deck_text(
    model: RomModel,
    case: str,
    moment_nmm: float,
    nlgeom: bool = True,
    initial_increment: float = 0.1,
    min_increment: float = 1e-4,
    max_increment: float = 0.25,
    max_increments: int = 100,
    provenance: str = "",
    average_force_n: float | None = None,
) -> str:
    """The complete ccx deck of one load case: model data, rigid bodies, fixation, one static step with
    the pure moment on the top's ROT NODE, node prints of every endplate node and the ROT NODE."""
    if case not in LOAD_CASES:
        raise ValueError(f"unknown load case '{case}' (one of {list(LOAD_CASES)})")
    fe = model.fe
    n = len(fe.nodes)
    parts = [model_to_inp_text(fe, provenance=provenance)]
    extra, rb, next_id = [], [], n + 1
    rot_top = None
    for v, nodes in model.rigid_nodes.items():
        c = fe.nodes[nodes].mean(0)
        ref, rot = next_id, next_id + 1
        next_id += 2
        extra += [f"{ref}, {c[0]:.6f}, {c[1]:.6f}, {c[2]:.6f}\n", f"{rot}, {c[0]:.6f}, {c[1]:.6f}, {c[2]:.6f}\n"]
        rb.append((v, ref, rot, nodes))
        if v == model.top:
            rot_top = rot
    if rot_top is None:
        raise RomError(f"the top vertebra {model.top} has no rigid body to load")
    # extra nodes right after the mesh: ccx allocates memory by the largest node id
    parts.append("*NODE, NSET=RBNODES\n" + "".join(extra))
    from spinecohort.fe.abaqus import format_id_list

    for v, ref, rot, nodes in rb:
        parts.append(f"*NSET, NSET=RB_{v}\n" + format_id_list(nodes + 1))
        parts.append(f"*RIGID BODY, NSET=RB_{v}, REF NODE={ref}, ROT NODE={rot}\n")
    parts.append("*NSET, NSET=FIXED\n" + format_id_list(np.unique(model.fixed_nodes) + 1))
    parts.append(
        "*NSET, NSET=EPNODES\n" + format_id_list(np.unique(np.concatenate(list(model.endplate_nodes.values()))) + 1)
    )
    parts.append(f"*NSET, NSET=ROTTOP\n{rot_top}\n")
    parts.append("*BOUNDARY\nFIXED, 1, 3\n")
    m = load_vector_nmm(model, case, moment_nmm)
    step = f"*STEP, NLGEOM, INC={max_increments}\n" if nlgeom else "*STEP\n"
    parts.append(step + "*STATIC\n")
    if nlgeom:
        parts.append(f"{initial_increment}, 1.0, {min_increment}, {max_increment}\n")
    if nlgeom:
        # more Newton iterations before a cutback (IC 16 -> 200) and more cutbacks (IA 5 -> 20) than ccx's
        # defaults: with tension-only springs and the exponential fibre law both switching on, the default
        # controls stalled the test model's L3-L4 extension at 47 % of the load; these converge (docs/rom.md)
        parts.append("*CONTROLS, PARAMETERS=TIME INCREMENTATION\n20, 30, 9, 200, 10, 4, , 20\n")
        if average_force_n:
            # ccx accepts an iteration when the largest residual is < 0.5 % of the model's average nodal
            # force.  Under a pure moment that average is ~0.3 N (soft tissue, few loaded nodes), so the
            # criterion asked for 0.002 N on rigid-body resultants and stalled the lumbar runs for dozens
            # of iterations per increment; a user-defined reference force fixes the scale (docs/rom.md).
            parts.append(
                f"*CONTROLS, PARAMETERS=FIELD\n0.005, 0.01, 0.01, {average_force_n!r}, 0.02, 1e-5, 1e-3, 1e-8\n"
            )
    parts.append("*CLOAD\n" + "".join(f"{rot_top}, {k + 1}, {m[k]:.6f}\n" for k in range(3)))
    parts.append("*NODE PRINT, NSET=ROTTOP\nU\n*NODE PRINT, NSET=EPNODES\nU\n*END STEP\n")
    return "".join(parts)
