"""From the hex template (+ any model's node coordinates) to an Abaqus/CalculiX deck, STL and VTU.

Materials are of the seed's Table 2 kind (linear elastic bone, hyperelastic disc, nonlinear ligaments);
values are literature defaults, each with its source below.  The calibrated fibre-reinforced annulus and the
load cases belong to the FE-validation stage; here the deck carries named materials and sections so that it
is complete and solver-ready.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .abaqus import FEModel, LinearElastic, MooneyRivlin, Section, write_inp, write_vtu
from .hex_template import LIGAMENT_GROUPS, HexTemplate

#: (E MPa, nu) of the linear-elastic tissues.  Cortical/cancellous bone: Goel et al. 1995 and
#: Shirazi-Adl et al. 1986 (12000 / 100 MPa); cartilage endplate: Lu et al. 1996 (24 MPa, 0.4).
LINEAR = {"CORTICAL": (12000.0, 0.3), "CANCELLOUS": (100.0, 0.2), "CEP": (24.0, 0.4)}
#: Mooney-Rivlin (C10, C01 MPa, D1 1/MPa): nucleus nearly incompressible, annulus ground substance
#: (Schmidt et al. 2007, Clin Biomech 22:377).  D1 > 0 because ccx replaces D1 = 0 by its own default.
HYPERELASTIC = {"NP": (0.12, 0.03, 0.0005), "AF": (0.18, 0.045, 0.1)}
#: Ligament stiffness N/mm (tension only), from Shirazi-Adl et al. 1986 / Rohlmann et al. 2006 initial
#: stiffnesses; per side where a group has a left and a right element.
LIGAMENT_STIFFNESS = {"ALL": 33.0, "PLL": 20.4, "LF": 27.2, "CL": 33.9, "ISL": 11.5, "SSL": 23.7, "ITL": 10.0}
SHELL_THICKNESS_MM = 1.0  # cortical shell of the surface-modelled bones


def ligament_table(k_n_per_mm: float, max_elongation_mm: float = 20.0) -> tuple[tuple[float, float], ...]:
    """(force N, elongation mm) pairs, ascending in elongation: zero force in compression (tension only in
    an NLGEOM step), linear stiffness in tension."""
    return ((0.0, -10.0), (0.0, 0.0), (k_n_per_mm * max_elongation_mm, max_elongation_mm))


def fe_model(template: HexTemplate, points: np.ndarray | None = None, hex_type: str = "C3D8",
             include_all: bool = True, heading: str = "spinecohort model") -> FEModel:
    """The template as an FEModel with the given node coordinates (default: the template's own)."""
    pts = template.nodes if points is None else np.asarray(points, dtype=np.float64)
    if pts.shape != template.nodes.shape:
        raise ValueError(f"points have shape {pts.shape}, the template has {template.nodes.shape}")
    lig_keep = np.ones(len(template.ligaments), bool)
    if not include_all:
        lig_keep[template.elsets["LIG_ALL"]] = False
    blocks = {"HEXES": (hex_type, template.hexes), "SURFACES": ("S3", template.tris),
              "LIGAMENTS": ("SPRINGA", template.ligaments[lig_keep])}
    offset = {"hex": 0, "tri": len(template.hexes), "lig": len(template.hexes) + len(template.tris)}
    lig_new = np.cumsum(lig_keep) - 1
    elsets = {}
    for name, idx in template.elsets.items():
        kind = template.elset_kind[name]
        if kind == "lig":
            idx = lig_new[idx[lig_keep[idx]]]
            if len(idx) == 0:
                continue
        elsets[name] = offset[kind] + np.asarray(idx)
    materials = [LinearElastic(k, *v) for k, v in LINEAR.items()]
    materials += [MooneyRivlin(k, *v) for k, v in HYPERELASTIC.items()]
    sections = []
    for name, kind in template.elset_kind.items():
        if name not in elsets:
            continue
        if kind == "hex":
            tissue = name.rsplit("_", 1)[1]
            mat = {"CORE": "CANCELLOUS", "SHELL": "CORTICAL"}.get(tissue, tissue)
            sections.append(Section(elset=name, material=mat))
        elif kind == "tri":
            sections.append(Section(elset=name, material="CORTICAL", thickness_mm=SHELL_THICKNESS_MM))
        else:
            group = name.split("_", 1)[1]
            sections.append(Section(elset=name, spring_force_elongation=ligament_table(LIGAMENT_STIFFNESS[group])))
    return FEModel(nodes=pts, element_blocks=blocks, node_sets=dict(template.nsets), element_sets=elsets,
                   materials=materials, sections=sections, heading=heading)


def write_model_files(template: HexTemplate, points: np.ndarray, out: str | Path, fmt: str,
                      heading: str = "spinecohort model") -> Path:
    """Write one model as ``inp`` (Abaqus/CalculiX deck) or ``vtu``."""
    model = fe_model(template, points, heading=heading)
    if fmt == "inp":
        return write_inp(model, out, provenance=heading)
    if fmt == "vtu":
        return write_vtu(model, out)
    raise ValueError(f"unknown FE format '{fmt}' (inp | vtu)")


__all__ = ["fe_model", "write_model_files", "ligament_table", "LIGAMENT_GROUPS"]
