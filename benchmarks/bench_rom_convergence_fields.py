"""Which tissue's discretisation moves the ROM between two template resolutions: the base resolution with one
`TemplateResolution` field at a time set to the finer one's value, the given units and load cases solved.

Run (after rule rom_convergence, whose table gives the base and finer ROM):
    python benchmarks/bench_rom_convergence_fields.py --results results --units T6T7 --cases lateral_left lateral_right
Writes <results>/rom/convergence_fields.csv and prints, per field, the ROM (deg) and its change (%) from the base
resolution's, next to the finer resolution's change, and the units' disc cross-section and height as meshed at the
base, each variant and the finer resolution.  One ccx at a time, one thread.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import yaml

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.fe.materials import materials_from_config
from spinecohort.layout import Layout
from spinecohort.mesh.morph import MorphParameters
from spinecohort.rom.convergence import disc_geometry, morphed_template, one_field_variants, solve_resolution
from spinecohort.rom.run import solver_config
from spinecohort.ssm.model import SSM


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", default="results", help="results folder of a default run (SSM, cohort, convergence)")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--base", default="coarse")
    ap.add_argument("--finer", default="medium")
    ap.add_argument("--units", nargs="+", required=True)
    ap.add_argument("--cases", nargs="+", required=True)
    args = ap.parse_args()
    cfg = yaml.safe_load(Path(args.config).read_text())
    lay = Layout(args.results)
    ssm, cohort = SSM.load(lay.ssm), load_cohort_npz(lay.cohort)
    rom = {**solver_config(cfg["rom"]), "threads": 1}
    rows, geometry = [], []
    variants = {args.base: args.base, **one_field_variants(args.base, args.finer), args.finer: args.finer}
    for field, res in variants.items():
        template, nodes, mesh = morphed_template(
            res,
            ssm.mean,
            cohort.faces,
            cohort.landmarks,
            MorphParameters(**cfg["morph"]),
            cfg["template"]["cep_diameter_fraction"],
        )
        geometry.append(disc_geometry(template, nodes, args.units).assign(variant=field))
        if field in (args.base, args.finer):  # solved by rule rom_convergence
            continue
        work = Path(lay.path("rom", "convergence_fields", field))
        t = solve_resolution(
            template, nodes, rom, args.units, args.cases, work, materials_from_config(cfg["fe"]), field
        )
        rows.append(t.assign(field=field, value=getattr(res, field), model_inverted=mesh["model_inverted"]))
    table = pd.concat(rows, ignore_index=True)
    conv = pd.read_csv(lay.rom_convergence()).pivot_table(
        index=["unit", "load_case"], columns="resolution", values="rom_deg"
    )
    ref = conv.loc[list(zip(table["unit"], table["load_case"]))].reset_index(drop=True)
    table["change_from_base"] = (table["rom_deg"] - ref[args.base]) / ref[args.base].abs()
    table[f"{args.finer}_change_from_base"] = (ref[args.finer] - ref[args.base]) / ref[args.base].abs()
    out = lay.path("rom", "convergence_fields.csv")
    table.to_csv(out, index=False)
    cols = ["field", "value", "unit", "load_case", "rom_deg", "change_from_base", f"{args.finer}_change_from_base"]
    cols += ["unit_elements", "solve_s", "peak_rss_mb"]
    with pd.option_context("display.width", 200):
        print(table[cols].round(4).to_string(index=False))
    print(f"written {out}")
    geo = pd.concat(geometry, ignore_index=True)
    print("disc cross-section (endplate areas, mm2) and mean height (mm) as meshed:")
    print(
        geo.pivot_table(
            index="variant", columns="unit", values=["upper_endplate_mm2", "mean_height_mm"], sort=False
        ).round(1)
    )


if __name__ == "__main__":
    main()
