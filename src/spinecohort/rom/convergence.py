"""Mesh convergence of the range of motion: the hex template at several `TEMPLATE_RESOLUTIONS`, each built and
morphed onto the SSM mean by the pipeline's own functions (`build_template`, `morph_template`), its functional
units solved under the validation's pure moments (`solve_model`), and the ROM change between successive
resolutions judged against a relative criterion (docs/explanation/validation.md "Mesh convergence").
Units: mm, degrees, seconds, MB."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.fe.materials import FEMaterials
from spinecohort.mesh.morph import MorphParameters, morph_template
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, HexTemplate, TemplateResolution, build_template
from spinecohort.rom.run import Settings, solve_model, units_only
from spinecohort.rom.submodel import extract_rom_model, parse_unit

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ConvergenceStudy:
    """The ``rom.convergence`` config block: resolutions from coarse to fine, the functional units and load
    cases solved at each, and the largest accepted relative ROM change (fraction) between the default resolution
    and the next finer one."""

    resolutions: tuple[str, ...]
    units: tuple[str, ...]
    load_cases: tuple[str, ...]
    max_change: float = 0.05

    @classmethod
    def from_config(cls, block: dict) -> ConvergenceStudy:
        study = cls(
            tuple(block["resolutions"]),
            tuple(block["units"]),
            tuple(block["load_cases"]),
            float(block.get("max_change", 0.05)),
        )
        unknown = [r for r in study.resolutions if r not in TEMPLATE_RESOLUTIONS]
        if unknown:
            raise ValueError(
                f"rom.convergence.resolutions: {unknown} are not template resolutions {list(TEMPLATE_RESOLUTIONS)}"
            )
        if len(study.resolutions) < 2:
            raise ValueError("rom.convergence.resolutions: a convergence study needs at least two resolutions")
        for u in study.units:
            parse_unit(u)  # a clear error for a misspelt unit before any solve
        return study

    def judged_pair(self, default: str) -> tuple[str, str]:
        """(default, the next finer resolution): the pair the criterion judges.  The default must be one of the
        study's resolutions other than the finest, or there is nothing finer to judge it against."""
        if default not in self.resolutions[:-1]:
            raise ValueError(
                f"rom.convergence.resolutions {list(self.resolutions)}: the default resolution '{default}' "
                "(template.resolution) must be one of them and not the finest"
            )
        i = self.resolutions.index(default)
        return default, self.resolutions[i + 1]


#: the `TemplateResolution` fields that set the element counts, with the tissue each one refines
DISCRETISATION_FIELDS = {
    "core_cells": "cross-section: nucleus core and elements around (bodies and discs)",
    "rings": "cross-section: rings from the core out (annulus, cortical shell)",
    "body_layers": "vertebral bodies: element layers",
    "disc_layers": "discs: element layers between the cartilage endplates",
}


def one_field_variants(base: str, finer: str) -> dict[str, TemplateResolution]:
    """``base`` with one discretisation field at a time set to ``finer``'s value: field name -> resolution
    (only the fields that differ).  Solving them says which tissue's discretisation moves the ROM."""
    a, b = TEMPLATE_RESOLUTIONS[base], TEMPLATE_RESOLUTIONS[finer]
    return {
        f: dataclasses.replace(a, **{f: getattr(b, f)}) for f in DISCRETISATION_FIELDS if getattr(a, f) != getattr(b, f)
    }


def morphed_template(
    resolution: str | TemplateResolution,
    mean_points: np.ndarray,
    mean_faces: np.ndarray,
    landmarks,
    morph: MorphParameters,
    cep_diameter_fraction: float = 1.0,
    fibres: dict[str, int] | None = None,
) -> tuple[HexTemplate, np.ndarray, dict]:
    """The template at ``resolution`` (a preset's name or a `TemplateResolution`) built on the mean and morphed onto it, as rules hex_template and
    morph_template do, with `fibres` per ligament group as rule hex_template bundles them: (template, morphed nodes
    (N, 3) mm, mesh summary).  The summary counts the whole
    model's hexes with a scaled Jacobian <= 0 (``inverted``); the morph rule refuses such a mean, the study
    records it and solves the units, whose own hexes `solve_model` checks."""
    preset = TEMPLATE_RESOLUTIONS[resolution] if isinstance(resolution, str) else resolution
    res = dataclasses.replace(preset, cep_diameter_fraction=float(cep_diameter_fraction))
    template = build_template(mean_points, mean_faces, landmarks, res, fibres=fibres)
    nodes, _ = morph_template(template, mean_points, mean_faces, landmarks, morph)
    sj = scaled_jacobian(nodes, template.hexes)
    bad = np.flatnonzero(sj <= 0)
    where = sorted(
        {
            name
            for name, idx in template.elsets.items()
            if template.elset_kind[name] == "hex" and np.isin(idx, bad).any()
        }
    )
    summary = dict(
        resolution=resolution if isinstance(resolution, str) else "custom",
        model_hex_nodes=template.n_hex_nodes,
        model_hexes=len(template.hexes),
        model_min_scaled_jacobian=float(sj.min()),
        model_inverted=len(bad),
        inverted_sets=" ".join(where),
    )
    log.info(
        "%s: %d hex nodes, %d hexes, min scaled Jacobian %.3f, %d inverted %s",
        resolution,
        template.n_hex_nodes,
        len(template.hexes),
        sj.min(),
        len(bad),
        where,
    )
    return template, nodes, summary


def solve_resolution(
    template: HexTemplate,
    nodes: np.ndarray,
    rom: dict,
    units: list[str],
    load_cases: list[str],
    workdir: str | Path,
    materials: FEMaterials,
    label: str,
) -> pd.DataFrame:
    """ROM (deg) of functional ``units`` (e.g. T10T11) under ``load_cases`` on one resolution's morphed mean
    (`solve_model` on the rib-free units, `units_only`, with the ``rom:`` block's solver settings), with each
    unit's node and element counts."""
    cfg = {**units_only(rom, units), "load_cases": list(load_cases)}
    table = solve_model(template, nodes, cfg, workdir, label, materials)
    settings = Settings.from_config(cfg)
    sizes = []
    for top, bottom in settings.units:
        model = extract_rom_model(
            template,
            nodes,
            top,
            bottom,
            materials=materials,
            hex_type=settings.hex_type,
            disc_hex_type=settings.disc_hex_type,
            nucleus_hex_type=settings.nucleus_hex_type,
            facets=materials.facets,
        )
        sizes.append(dict(unit=f"{top}-{bottom}", unit_nodes=len(model.fe.nodes), unit_elements=model.fe.n_elements))
    return table.merge(pd.DataFrame(sizes), on="unit", how="left")


def convergence_table(rom: pd.DataFrame, resolutions: list[str], default: str, max_change: float) -> pd.DataFrame:
    """Per unit, segment and load case, the ROM at each resolution and its relative change to the next finer.

    rom: rows ``resolution, unit, segment, load_case, rom_deg`` (other columns are carried along).  Adds
    ``change_to_finer`` = (ROM - ROM_finer) / |ROM_finer| (fraction; NaN at the finest or without the next
    resolution's solve) and, on the default resolution's rows, ``converged`` = |change_to_finer| < max_change
    (None on the other rows)."""
    order = {r: i for i, r in enumerate(resolutions)}
    missing = set(rom["resolution"]) - set(order)
    if missing:
        raise ValueError(f"the ROM table has resolutions {sorted(missing)} outside the study's {resolutions}")
    if default not in resolutions[:-1]:
        raise ValueError(f"the default resolution '{default}' must be one of {resolutions[:-1]} (not the finest)")
    key = ["unit", "segment", "load_case"]
    # units and load cases in the order solved (the config's), resolutions coarse to fine
    first = {c: {v: i for i, v in enumerate(dict.fromkeys(rom[c]))} for c in key}
    t = (
        rom.assign(_order=rom["resolution"].map(order))
        .sort_values(key + ["_order"], key=lambda col: col.map(first[col.name]) if col.name in first else col)
        .reset_index(drop=True)
    )
    finer = t.groupby(key)["rom_deg"].shift(-1)
    finer_order = t.groupby(key)["_order"].shift(-1)
    # only a change to the next resolution of the study counts: a missing finer solve leaves NaN
    finer = finer.where(finer_order == t["_order"] + 1)
    t["change_to_finer"] = (t["rom_deg"] - finer) / finer.abs()
    judged = t["resolution"] == default
    verdict = t["change_to_finer"].abs() < max_change
    # a default case without its finer solve fails (NaN < max_change is False): nothing shows it converged
    t["converged"] = pd.Series(np.where(judged, verdict, None), dtype=object)
    return t.drop(columns="_order")


def verdict(table: pd.DataFrame) -> bool:
    """True when there are judged cases and every one converged."""
    judged = table["converged"].dropna()
    return bool(len(judged)) and bool(judged.astype(bool).all())


def resolution_summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per resolution: mesh sizes, summed ccx solve time (s) and the largest ccx peak memory (MB)."""
    agg = table.drop_duplicates(["resolution", "unit", "load_case"]).groupby("resolution", sort=False)
    out = agg.agg(
        model_hexes=("model_hexes", "first"),
        model_inverted=("model_inverted", "first"),
        unit_nodes=("unit_nodes", "max"),
        unit_elements=("unit_elements", "max"),
        solves=("solve_s", "size"),
        solve_s=("solve_s", "sum"),
        max_case_solve_s=("solve_s", "max"),
        peak_rss_mb=("peak_rss_mb", "max"),
    )
    return out.reset_index()


def convergence_markdown(table: pd.DataFrame, default: str, finer: str, max_change: float) -> str:
    """The study as Markdown: ROM (deg) per resolution and the % changes, the verdict, and the cost table."""
    res = list(dict.fromkeys(table["resolution"]))
    wide = table.pivot_table(index=["unit", "load_case"], columns="resolution", values="rom_deg", sort=False)[res]
    change = table.pivot_table(index=["unit", "load_case"], columns="resolution", values="change_to_finer", sort=False)
    head = ["unit", "load case"] + [f"{r} (deg)" for r in res] + [f"{a}→{b} (%)" for a, b in zip(res, res[1:])]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (unit, case), row in wide.iterrows():
        changes = [change.loc[(unit, case), a] if a in change.columns else np.nan for a in res[:-1]]
        cells = [unit, case] + [f"{v:.3f}" for v in row] + [f"{100 * c:+.1f}" for c in changes]
        lines.append("| " + " | ".join(cells) + " |")
    judged = table[table["converged"].notna()]
    n_ok = int(judged["converged"].astype(bool).sum())
    worst = judged.loc[judged["change_to_finer"].abs().idxmax()] if len(judged) else None
    lines += [
        "",
        f"Criterion: |ROM_{finer} − ROM_{default}| / ROM_{finer} < {100 * max_change:g} % for every case; "
        f"{n_ok} of {len(judged)} cases pass, verdict: **{'converged' if verdict(table) else 'not converged'}**"
        + (
            f" (largest change {100 * worst['change_to_finer']:+.1f} %, {worst['unit']} {worst['load_case']})."
            if worst is not None
            else "."
        ),
        "",
    ]
    summ = resolution_summary(table)
    cols = [
        "resolution",
        "model hexes",
        "inverted (model)",
        "unit nodes",
        "unit elements",
        "solves",
        "ccx s",
        "max s/case",
        "peak MB",
    ]
    lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in summ.iterrows():
        lines.append(
            f"| {r['resolution']} | {r['model_hexes']} | {r['model_inverted']} | {r['unit_nodes']} | {r['unit_elements']} | "
            f"{r['solves']} | {r['solve_s']:.0f} | {r['max_case_solve_s']:.0f} | {r['peak_rss_mb']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def disc_geometry(template: HexTemplate, nodes: np.ndarray, units: list[str]) -> pd.DataFrame:
    """Per functional unit's disc: the area (mm²) of its two bounding endplate node layers (the disc's
    cross-section as meshed, the quads' areas summed), the upper one's projected on the plane across the disc's
    axis (centre to centre; the outline without the concave endplate's depth) and its mean height (mm, node to
    node between them)."""
    from spinecohort.fe.connections import body_layer

    n2, quads = len(template.grid.nodes), template.grid.quads
    rows = []
    for unit in units:
        up, lo = parse_unit(unit)
        a = nodes[body_layer(template, up, 0.0) * n2 + np.arange(n2)]
        b = nodes[body_layer(template, lo, 1.0) * n2 + np.arange(n2)]
        axis = (a.mean(0) - b.mean(0)) / np.linalg.norm(a.mean(0) - b.mean(0))

        def doubled_areas(p):  # (n_quads, 3): each quad's normal times twice its area
            q = p[quads]
            return np.cross(q[:, 2] - q[:, 0], q[:, 3] - q[:, 1])

        rows.append(
            dict(
                unit=f"{up}-{lo}",
                upper_endplate_mm2=0.5 * float(np.linalg.norm(doubled_areas(a), axis=1).sum()),
                lower_endplate_mm2=0.5 * float(np.linalg.norm(doubled_areas(b), axis=1).sum()),
                upper_projected_mm2=0.5 * float(np.abs(doubled_areas(a) @ axis).sum()),
                mean_height_mm=float(np.linalg.norm(a - b, axis=1).mean()),
            )
        )
    return pd.DataFrame(rows)
