"""The discs' cross-section as meshed at each template resolution and endplate rim depth (`morph.rim_depth_mm`):
the ray morph's endplate outline should be the bone's, not the mesh's.

Run (after rules cohort and ssm of a default run):
    python benchmarks/bench_endplate_outline.py --results results --depths 1 2 3
Prints, per rim depth, each disc's upper endplate area (mm2; its quads summed, and projected across the disc's
axis) per resolution and its largest change between two neighbouring resolutions (%), and the whole model's
inverted hexes (scaled Jacobian <= 0).  No solves: ~2 s a morph.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pandas as pd
import yaml

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.layout import Layout
from spinecohort.mesh.morph import MorphParameters
from spinecohort.rom.convergence import disc_geometry, morphed_template
from spinecohort.ssm.model import SSM


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", default="results", help="results folder of a default run (SSM, cohort)")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--resolutions", nargs="+", default=["coarser", "coarse", "medium", "fine"])
    ap.add_argument("--units", nargs="+", default=["T6T7", "T10T11", "T12L1", "L3L4", "L4L5"])
    ap.add_argument("--depths", nargs="+", type=float, default=[2.0], help="morph.rim_depth_mm values (mm)")
    args = ap.parse_args()
    cfg = yaml.safe_load(Path(args.config).read_text())
    lay = Layout(args.results)
    ssm, cohort = SSM.load(lay.ssm), load_cohort_npz(lay.cohort)
    base = MorphParameters(**cfg["morph"])
    for depth in args.depths:
        rows, inverted = [], {}
        for res in args.resolutions:
            template, nodes, mesh = morphed_template(
                res,
                ssm.mean,
                cohort.faces,
                cohort.landmarks,
                dataclasses.replace(base, rim_depth_mm=depth),
                cfg["template"]["cep_diameter_fraction"],
            )
            rows.append(disc_geometry(template, nodes, args.units).assign(resolution=res))
            inverted[res] = f"{mesh['model_inverted']} ({mesh['inverted_sets'] or '-'})"
        geo = pd.concat(rows)
        for column in ("upper_endplate_mm2", "upper_projected_mm2"):
            area = geo.pivot(index="unit", columns="resolution", values=column)[args.resolutions]
            area["largest step %"] = (area.pct_change(axis=1).abs().max(axis=1) * 100).round(1)
            print(f"rim depth {depth} mm: {column} per resolution")
            print(area.round(1).to_string())
        print("inverted hexes:", inverted)


if __name__ == "__main__":
    main()
