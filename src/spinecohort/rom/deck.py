"""The complete CalculiX deck of one pure-moment load case of a ROM sub-model: its model data and the
pure-moment step of `spinecohort.fe.pure_moment` on its rigid top vertebra, with node prints of every endplate
node.  Units: mm, N, N.mm (radians only inside the deck)."""

from __future__ import annotations

import numpy as np

from spinecohort.fe.pure_moment import LOAD_CASES, pure_moment_text
from spinecohort.fe.writers import model_to_inp_text
from spinecohort.rom.loads import with_load_prints
from spinecohort.rom.submodel import RomError, RomModel

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
    correction_tolerance: float = 0.01,
    load_nmm: np.ndarray | None = None,
    guided: bool = False,
    load_prints: bool = True,
) -> str:
    """The complete ccx deck of one load case: model data, rigid bodies, fixation, one static step with
    the pure moment on the top's ROT NODE, node prints of every endplate node, the ROT NODE and the fixed
    nodes' reaction forces.  load_nmm: the ROT NODE's *CLOAD (3,) N.mm instead of the load case's moment
    vector (`spinecohort.rom.reaction.generalised_load`: the load that exerts that moment at a rotation).
    guided: the top turns about the load's axis only (`pure_moment_text`), `run_case`'s last attempt.
    load_prints: also print what the nucleus pressures and facet forces are read from (`spinecohort.rom.loads`;
    output only: the solution is the same)."""
    if case not in LOAD_CASES:
        raise ValueError(f"unknown load case '{case}' (one of {list(LOAD_CASES)})")
    if model.top not in model.rigid_nodes:
        raise RomError(f"the top vertebra {model.top} has no rigid body to load")
    deck = model_to_inp_text(model.fe, provenance=provenance) + pure_moment_text(
        model.fe.nodes,
        model.rigid_nodes,
        model.top,
        model.fixed_nodes,
        {"EPNODES": np.unique(np.concatenate(list(model.endplate_nodes.values())))},
        load_vector_nmm(model, case, moment_nmm) if load_nmm is None else np.asarray(load_nmm, dtype=np.float64),
        nlgeom=nlgeom,
        initial_increment=initial_increment,
        min_increment=min_increment,
        max_increment=max_increment,
        max_increments=max_increments,
        average_force_n=average_force_n,
        correction_tolerance=correction_tolerance,
        guided=guided,
    )
    return with_load_prints(deck, model.fe) if load_prints else deck
