"""Benchmark: the facet joints of a model from its own articular surfaces, and the ROM of functional units.

Run: python benchmarks/bench_facets.py [--results results] [--model model_08403] [--config config/config.yaml]
         [--points 16] [--rom --units T2T3,T6T7,T10T11,L3L4 --out /tmp/spinecohort_bench_facets] [key=value ...]
Prints per joint (upper vertebra of the segment, side) the contact plane's angle to the transverse and to the
frontal plane (deg, `spinecohort.anatomy.morphometry.facet_angles_deg`: + = the superior facet faces medially) next to
Masharawi et al. 2004's range for its level (angle to the frontal plane), the facing part's projected area (mm^2)
the bone-to-bone gap along the normal (median, min, max over --points contact points, mm) and the extension stop's
bone gap: how far the IAP tip travels along its extension path before it meets the vertebra below (mm, bare
bone; `spinecohort.fe.tip_gap`, 8 = meets nothing within 8 mm).  Needs a template
built with the insertion sites (a real-bone cohort).  With --rom: the six load cases of each unit, one ccx thread
(`spinecohort.rom.run.solve_model`), config overrides as dotted key=value (e.g. fe.facets.struts_per_joint=1).
With --thoracic-transverse-deg D: what the thoracic joints' inclination does, the T1-T2 ... T10-T11 contact normals
turned to D deg to the transverse plane (their frontal angle and contact points kept; a what-if on the solver's
side, the bones stay as they are).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

#: Masharawi et al. 2004 (Spine 29:1755): facet angle to the frontal plane (deg) by region of the lower vertebra
MASHARAWI_FRONTAL_DEG = {**{f"T{i}": (25, 30) for i in range(1, 12)}, "T12": (56, 64), "L1": (56, 64), "L2": (56, 64)}
MASHARAWI_FRONTAL_DEG.update({"L3": (34, 50), "L4": (34, 50), "L5": (34, 50)})


def facet_table(template, points, n_points: int) -> list[dict]:
    """One row per joint with articular surfaces: angles, facing area, gaps."""
    from spinecohort.anatomy.morphometry import facet_angles_deg
    from spinecohort.fe.facets import _joints, facet_pairs, joint_geometries
    from spinecohort.fe.tip_gap import tip_stops

    pairs = facet_pairs(template)
    frames, joints = _joints(template, points, pairs)
    _, tip_gap = tip_stops(template, points, pairs, joints, frames, 0.0)
    rows = []
    for (up, lo, side), geo, tip in zip(joints, joint_geometries(template, points, pairs, n_points), tip_gap):
        if geo is None:
            continue
        t, f = facet_angles_deg(geo.normal, frames[up][0], side)
        lo_range = MASHARAWI_FRONTAL_DEG.get(up, (np.nan, np.nan))  # the superior facet belongs to `lo`
        lo_range = MASHARAWI_FRONTAL_DEG.get(lo, lo_range)
        rows.append(
            {
                "joint": f"{up}-{lo}",
                "side": "R" if side > 0 else "L",
                "transverse_deg": round(t, 1),
                "frontal_deg": round(f, 1),
                "masharawi_frontal_deg": f"{lo_range[0]}-{lo_range[1]}",
                "facing_mm2": round(geo.facing_area_mm2),
                "gap_median_mm": round(float(np.median(geo.gaps)), 2),
                "gap_min_mm": round(float(geo.gaps.min()), 2),
                "gap_max_mm": round(float(geo.gaps.max()), 2),
                "tip_gap_mm": round(float(tip), 2),
            }
        )
    return rows


def tilt_thoracic_joints(transverse_deg: float) -> None:
    """Make `spinecohort.fe.facets.joint_geometries` turn the contact normal of every joint T1-T2 ... T10-T11 to
    ``transverse_deg`` to the transverse plane, its frontal angle kept (`FacetContact.normal`'s convention)."""
    from dataclasses import replace

    import spinecohort.fe.facets as facets
    from spinecohort.anatomy.morphometry import facet_angles_deg

    measured = facets.joint_geometries

    def tilted(template, points, pairs, n_points):
        frames, joints = facets._joints(template, points, pairs)
        out = []
        for geo, (up, _, side) in zip(measured(template, points, pairs, n_points), joints):
            if geo is None or up not in [f"T{k}" for k in range(1, 11)]:
                out.append(geo)
                continue
            frame = frames[up][0]
            f = np.radians(facet_angles_deg(geo.normal, frame, side)[1])
            t = np.radians(transverse_deg)
            n = np.sin(t) * (np.cos(f) * -frame[:, 1] - np.sin(f) * side * frame[:, 0]) + np.cos(t) * frame[:, 2]
            out.append(replace(geo, normal=n / np.linalg.norm(n)))
        return out

    facets.joint_geometries = tilted


def main() -> None:
    import pandas as pd

    from spinecohort.fe.export import read_deck_points
    from spinecohort.fe.materials import materials_from_config
    from spinecohort.mesh.template import HexTemplate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results")
    ap.add_argument("--model", default="model_08403")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--points", type=int, default=16)
    ap.add_argument("--rom", action="store_true")
    ap.add_argument("--units", default="T2T3,T6T7,T10T11,L3L4")
    ap.add_argument("--out", default="/tmp/spinecohort_bench_facets")
    ap.add_argument("--thoracic-transverse-deg", type=float, default=None)
    ap.add_argument("overrides", nargs="*", help="dotted config key=value (YAML value)")
    a = ap.parse_args()
    cfg = yaml.safe_load(Path(a.config).read_text())
    for kv in a.overrides:
        key, value = kv.split("=", 1)
        *path, leaf = key.split(".")
        d = cfg
        for k in path:
            d = d[k]
        d[leaf] = yaml.safe_load(value)
    results = Path(a.results)
    template = HexTemplate.load(results / "template" / "template.npz")
    points = read_deck_points(results / "models" / f"{a.model}.inp", template)
    rows = facet_table(template, points, a.points)
    if not rows:
        raise SystemExit("the template has no articular surfaces (a cohort without insertion sites)")
    print(pd.DataFrame(rows).to_markdown(index=False))
    if not a.rom:
        return
    from spinecohort.rom.run import solve_model, units_only

    if a.thoracic_transverse_deg is not None:
        tilt_thoracic_joints(a.thoracic_transverse_deg)
    rom = {**units_only(cfg["rom"], a.units.split(",")), "threads": 1}
    t0 = time.perf_counter()
    table = solve_model(template, points, rom, a.out, a.model, materials_from_config(cfg["fe"]))
    Path(a.out).mkdir(parents=True, exist_ok=True)
    table.to_csv(Path(a.out) / "rom.csv", index=False)
    print(table.pivot_table(index="segment", columns="load_case", values="rom_deg").round(2).to_markdown())
    print(f"load fractions {table['load_fraction'].min():.3f}-1, {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
