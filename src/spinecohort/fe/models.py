"""One virtual model on demand: weights from its ID, triangulated and hexahedral coordinates, Jacobian
check and repair, and its files (.stl, .inp, .vtu).  The same code serves the ``model_files`` rule and
``spinecohort export``."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spinecohort.cohort.landmarks import DISCS
from spinecohort.fe.export import fe_model
from spinecohort.mesh.contact import resolve_contact
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.repair import RepairError, untangle
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM
from spinecohort.store.zarr_store import n_models, weights_of

log = logging.getLogger(__name__)


def parse_model_id(name: str | int, n_modes: int, levels) -> int:
    """``"model_08403"`` or 8403 -> 8403, checked against the grid size."""
    try:
        i = int(str(name).removeprefix("model_"))
    except ValueError:
        raise ValueError(f"'{name}' is not a model ID (model_00000 ... model_NNNNN)") from None
    total = n_models(n_modes, levels)
    if not 0 <= i < total:
        raise ValueError(f"model ID {i} is outside the grid of {total} models (0 ... {total - 1})")
    return i


@dataclass
class VirtualModel:
    model_id: int
    weights: np.ndarray  # (m,) SD units
    tri_points: np.ndarray  # (N, 3) mm
    hex_points: np.ndarray  # (n_nodes, 3) mm, repaired if needed
    repair: dict


def hex_points_checked(template: HexTemplate, hex_ssm: HexSSM, weights: np.ndarray) -> tuple[np.ndarray, dict]:
    """Hex model coordinates for ``weights`` with collapsed discs opened (``hex_ssm.contact``) and every
    inverted element repaired (local untangling).  The report's ``level_offsets_mm`` (17, 3) is the
    distraction applied (zeros if none): add ``contact.tri_offsets`` of it to the triangulated model."""
    pts = hex_ssm.sample(weights)
    offsets = np.zeros((1, len(DISCS), 3))
    if hex_ssm.contact is not None:
        pts = pts[None].copy()
        _, offsets = resolve_contact(None, pts, hex_ssm.contact)
        pts = pts[0]
    n = template.n_hex_nodes
    sj = scaled_jacobian(pts[:n], template.hexes)
    report = {
        "invalid_before": int((sj <= 0).sum()),
        "min_sj_before": float(sj.min()),
        "nodes_moved": 0,
        "max_displacement_mm": 0.0,
        "distraction_mm": float(np.linalg.norm(offsets[0], axis=1).max()),
        "level_offsets_mm": offsets[0],
    }
    if report["invalid_before"]:
        fixed, rep = untangle(pts[:n], template.hexes, hex_ssm.mean[:n])
        pts = pts.copy()
        pts[:n] = fixed
        report.update(nodes_moved=int(len(rep.moved_nodes)), max_displacement_mm=float(rep.max_displacement_mm))
    sj = scaled_jacobian(pts[:n], template.hexes)
    report.update(invalid_after=int((sj <= 0).sum()), min_sj_after=float(sj.min()))
    return pts, report


def virtual_model(
    model: str | int, ssm: SSM, hex_ssm: HexSSM, template: HexTemplate, n_modes: int, levels
) -> VirtualModel:
    i = parse_model_id(model, n_modes, levels)
    w = np.asarray(weights_of(i, n_modes, levels), dtype=np.float64)
    try:
        pts, report = hex_points_checked(template, hex_ssm, w)
    except RepairError as exc:
        raise RepairError(f"model_{i:05d} (weights {w.tolist()} SD) cannot be repaired: {exc}") from exc
    tri = ssm.sample(w)
    if hex_ssm.contact is not None:
        tri = tri + hex_ssm.contact.tri_offsets(report["level_offsets_mm"][None])[0]
    return VirtualModel(i, w, tri, pts, report)


def check_load_options(fmt: str, load: str | None, guided: bool) -> None:
    """ValueError unless `load` (a pure-moment step) and `guided` fit the format: a load only in an ``inp``, and
    guided only with a load."""
    if guided and load is None:
        raise ValueError("--guided sets how the top of a --load deck turns: give --load too")
    if load is not None and fmt != "inp":
        raise ValueError(f"--load needs --format inp, not {fmt}")


def write_model(
    vm: VirtualModel,
    fmt: str,
    out: str | Path,
    template: HexTemplate,
    faces: np.ndarray,
    hex_type: str = "C3D8",
    materials=None,
    load: str | None = None,
    moment_nmm: float = 7500.0,
    top: str = "T1",
    guided: bool = False,
) -> Path:
    """Write ``stl`` (triangulated SSM shape), ``inp`` or ``vtu`` (hexahedral FE model).

    materials: `spinecohort.fe.materials.FEMaterials` (default: config/config.yaml's ``fe`` values).
    load: an ``inp`` with a pure-moment step (`spinecohort.fe.pure_moment.LOAD_CASES`: pelvis fixed, `moment_nmm`
    N.mm on vertebra `top`; guided: `top` turns about the load's axis only), ready for ``ccx -i <job>``; None: the
    model data alone."""
    from spinecohort.cohort.stl_io import write_stl
    from spinecohort.fe.export import NOT_ANATOMY, check_deck, write_deck
    from spinecohort.fe.writers import write_vtu

    check_load_options(fmt, load, guided)
    out = Path(out)
    name = f"model_{vm.model_id:05d}"
    heading = f"spinecohort {name}, weights (SD) {np.round(vm.weights, 3).tolist()}"
    if fmt == "stl":
        write_stl(out, vm.tri_points, faces, name=name)
    elif fmt == "inp":
        fe = fe_model(template, vm.hex_points, hex_type=hex_type, heading=heading, materials=materials)
        if load is None:
            write_deck(fe, out, provenance=heading)
        else:
            from spinecohort.fe.pure_moment import arch_skin_free, model_load_text

            check_deck(arch_skin_free(fe), str(out))  # the model the load deck carries is one body
            out.write_text(model_load_text(fe, template, load, top, moment_nmm, guided=guided))
    elif fmt == "vtu":
        # the deck's model without the connector and facet-strut lines (not anatomy): every element keeps its deck id
        fe = fe_model(template, vm.hex_points, hex_type=hex_type, heading=heading, materials=materials)
        write_vtu(fe, out, leave_out=NOT_ANATOMY)
    else:
        raise ValueError(f"unknown format '{fmt}' (inp | stl | vtu)")
    return out
