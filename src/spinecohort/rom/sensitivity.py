"""Sensitivity of the compared ROM to every calibrated parameter (config ``rom.sensitivity``).

Each parameter is set, one at a time, to the low and the high end of its published range (the rest at the
calibrated config values); the model's functional units (``rom.sensitivity.units``, the thoracic units and
L3-L4) are solved with the same code path as the rule ``rom_model`` (`spinecohort.rom.run.solve_model`)
and compared with the references (`spinecohort.rom.compare.validate_from_config`).  The table says how much
each compared ROM changes (deg) at each end: what drives what, measured rather than guessed.

A parameter is a dotted path into ``{"fe": <fe block>, "rom": <rom block>}``; ``*`` matches every key at
that level (e.g. ``fe.ligaments.*.area_mm2``), ``a|b`` the keys a and b (``fe.ligaments.ISL|SSL.area_mm2``).  ``scale: true`` makes low/high factors on the calibrated
value(s) instead of values.  Units: degrees, and the units of each parameter.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.fe.materials import materials_from_config
from spinecohort.mesh.template import HexTemplate
from spinecohort.rom.compare import orderings, validate_from_config
from spinecohort.rom.run import solve_model, solver_config, units_only

log = logging.getLogger(__name__)


def _leaves(node, keys: list[str]):
    """(parent dict, key) of every leaf a dotted path with ``*`` wildcards names."""
    head, rest = keys[0], keys[1:]
    names = list(node) if head == "*" else head.split("|")
    for k in names:
        if k not in node:
            raise KeyError(f"no key '{k}' (of {list(node)})")
        if rest:
            yield from _leaves(node[k], rest)
        else:
            yield node, k


def with_parameter(cfg: dict, path: str, value: float, scale: bool = False) -> dict:
    """A deep copy of ``cfg`` with the leaf (or leaves) at ``path`` set to ``value`` (or multiplied by it)."""
    out = copy.deepcopy(cfg)
    for parent, k in _leaves(out, path.split(".")):
        parent[k] = float(parent[k]) * value if scale else value
    return out


def parameter_value(cfg: dict, path: str) -> list[float]:
    """The calibrated value(s) at ``path``."""
    return [float(p[k]) for p, k in _leaves(cfg, path.split("."))]


def variants(cfg: dict) -> list[tuple[str, str, float, dict]]:
    """(parameter, level, value, config) of the baseline and of every parameter at its low and high end."""
    out = [("baseline", "calibrated", float("nan"), cfg)]
    for p in cfg["rom"]["sensitivity"]["parameters"]:
        for level in ("low", "high"):
            out.append(
                (p["name"], level, float(p[level]), with_parameter(cfg, p["path"], p[level], p.get("scale", False)))
            )
    return out


def unit_rom_config(rom: dict) -> dict:
    """The ``rom`` block restricted to the sensitivity's functional units (`units_only`)."""
    return units_only(rom, rom["sensitivity"]["units"])


def mesh_digest(template: HexTemplate, points: np.ndarray) -> str:
    """sha256 of what the solver reads of the mesh: node coordinates (mm, float64 bytes), element connectivity
    and every element and node set, so a cached variant is never reused for another template or deck."""
    h = hashlib.sha256(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    for a in (template.hexes, template.tris, template.ligaments):
        h.update(np.ascontiguousarray(a, dtype=np.int64).tobytes())
    for sets in (template.elsets, template.nsets):
        for name in sorted(sets):
            h.update(name.encode() + np.ascontiguousarray(sets[name], dtype=np.int64).tobytes())
    return h.hexdigest()


#: modules of the ROM stage that only compare or gather (their edits leave every solution valid)
_NOT_SOLVER = {"compare.py", "sensitivity.py", "modes.py", "convergence.py"}


@functools.cache  # the source of a running process does not change: read once, not per variant
def solver_code_digest() -> str:
    """sha256 of the source the solutions come from: every module of ``spinecohort.fe`` and of
    ``spinecohort.rom`` except the comparison and gathering ones, so a cached variant never outlives a change
    of the deck writer, the materials or the solver driver."""
    h = hashlib.sha256()
    pkg = Path(__file__).resolve().parents[1]
    for f in sorted([*(pkg / "fe").glob("*.py"), *(pkg / "rom").glob("*.py")]):
        if f.parent.name == "rom" and f.name in _NOT_SOLVER:
            continue
        h.update(f"{f.parent.name}/{f.name}".encode() + f.read_bytes())
    return h.hexdigest()


def variant_key(template: HexTemplate, points: np.ndarray, cfg: dict) -> str:
    """What one variant's solution depends on: the solver's code, the mesh, the fe block and the solver's part of
    the rom block (references, criteria, the sensitivity list and the thread count are left out: changing them
    re-solves nothing)."""
    # threads change the time, not the answer (ccx gave the same ROM to the last digit at 1 and 2 threads,
    # docs/explanation/validation.md "Sensitivity")
    solver_rom = {k: v for k, v in solver_config(unit_rom_config(cfg["rom"])).items() if k != "threads"}
    return json.dumps(
        {"code": solver_code_digest(), "mesh": mesh_digest(template, points), "fe": cfg["fe"], "rom": solver_rom},
        sort_keys=True,
    )


def solve_variant(
    template: HexTemplate, points: np.ndarray, cfg: dict, workdir: str | Path, model_id: str
) -> pd.DataFrame:
    """ROM table of the sensitivity units for one configuration; reused from ``workdir/rom.csv`` when the
    mesh and the configuration it was solved with (``workdir/config.json``, `variant_key`) are the same."""
    workdir = Path(workdir)
    key = variant_key(template, points, cfg)
    table_path, key_path = workdir / "rom.csv", workdir / "config.json"
    if table_path.exists() and key_path.exists() and key_path.read_text() == key:
        log.info("%s: reused (same mesh and configuration)", workdir.name)
        return pd.read_csv(table_path)
    table = solve_model(
        template, points, unit_rom_config(cfg["rom"]), workdir, model_id, materials_from_config(cfg["fe"])
    )
    workdir.mkdir(parents=True, exist_ok=True)
    key_path.unlink(missing_ok=True)  # a kill between the two writes leaves no key: the variant is solved again
    table.to_csv(table_path, index=False)
    key_path.write_text(key)
    return table


def sensitivity(
    template: HexTemplate, points: np.ndarray, cfg: dict, workdir: str | Path, model_id: str
) -> pd.DataFrame:
    """One row per variant (baseline, each parameter low/high) and compared ROM: our value, its change from
    the baseline (deg), in_range (calibration criterion), the load fraction reached (least over the variant's
    cases), the largest moment that guided a case (N.mm; 0 when every case was free); plus the lumbar
    orderings (flexion - extension, lateral - axial, deg) of the L units as rows with motion
    ``flexion_minus_extension`` / ``lateral_minus_axial``."""
    rows = []
    base_table = None
    for name, level, value, vcfg in variants(cfg):
        sub = Path(workdir) / (name if level == "calibrated" else f"{name}_{level}")
        if base_table is not None and vcfg == cfg:  # a parameter calibrated at one end of its range
            table = base_table
        else:
            table = solve_variant(template, points, vcfg, sub, model_id)
        if level == "calibrated":
            base_table = table
        val = validate_from_config(table, unit_rom_config(vcfg["rom"]))
        frac = float(table["load_fraction"].min())
        # a case solved by the guided attempt is a constrained value: how much moment held it (0: all free)
        guide = float(table["guide_moment_nmm"].max())
        for r in val.itertuples():
            rows.append(
                {
                    "parameter": name,
                    "level": level,
                    "value": value,
                    "segment": r.segment,
                    "motion": r.motion,
                    "side": r.side,
                    "rom_deg": r.model_deg,
                    "in_range": r.in_range,
                    "min_load_fraction": frac,
                    "max_guide_moment_nmm": guide,
                }
            )
        for o in orderings(table, mode="unit").itertuples():
            for motion, v in (
                ("flexion_minus_extension", o.flexion_minus_extension_deg),
                ("lateral_minus_axial", o.lateral_minus_axial_deg),
            ):
                rows.append(
                    {
                        "parameter": name,
                        "level": level,
                        "value": value,
                        "segment": o.segment,
                        "motion": motion,
                        "side": "one",
                        "rom_deg": v,
                        "in_range": bool(v > 0),
                        "min_load_fraction": frac,
                        "max_guide_moment_nmm": guide,
                    }
                )
        log.info("sensitivity %s %s (%s): %d rows, min load fraction %.2f", name, level, value, len(val), frac)
    out = pd.DataFrame(rows)
    base = out[out["parameter"] == "baseline"].set_index(["segment", "motion", "side"])["rom_deg"]
    out["change_deg"] = (
        out["rom_deg"] - base.reindex(pd.MultiIndex.from_frame(out[["segment", "motion", "side"]])).to_numpy()
    ).round(3)
    return out
