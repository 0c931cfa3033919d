"""Benchmark: hex template build, morphing per part, hex SSM transfer over the grid, .inp writing.

    python benchmarks/bench_template.py [--n 42] [--resolution default] [--template coarse]

Prints per-part registration time and surface distances, the inverted-element fractions of both transfer
methods over the full 7^5 grid, the Abaqus write time and the element-check throughput against VTK.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.cohort.synthetic import generate_cohort
from spinecohort.fe.export import fe_model
from spinecohort.fe.writers import write_inp
from spinecohort.mesh.hex_ssm import inverted_over_grid, transfer_fields
from spinecohort.mesh.morph import MorphParameters, morph_template
from spinecohort.mesh.quality.kernels import min_scaled_jacobian_nb
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, build_template
from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.procrustes import procrustes_align
from spinecohort.store.zarr_store import grid_weights


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=42)
    ap.add_argument("--resolution", default="default")
    ap.add_argument("--template", default="coarse")
    ap.add_argument("--grid-modes", type=int, default=5)
    a = ap.parse_args()
    c = generate_cohort(a.n, resolution=a.resolution)
    ssm = build_ssm(procrustes_align(c.vertices).aligned)
    t0 = time.perf_counter()
    tpl = build_template(ssm.mean, c.faces, c.landmarks, TEMPLATE_RESOLUTIONS[a.template])
    print(
        f"template ({a.template}): {tpl.n_nodes} nodes ({tpl.n_hex_nodes} hex), {len(tpl.hexes)} hexes, "
        f"{len(tpl.tris)} S3, {len(tpl.ligaments)} ligaments; built in {time.perf_counter() - t0:.2f} s"
    )
    t0 = time.perf_counter()
    nodes, rep = morph_template(tpl, ssm.mean, c.faces, c.landmarks, MorphParameters(max_iter=300, max_layers=3))
    print(f"morph: {time.perf_counter() - t0:.1f} s")
    with pd.option_context("display.width", 200):
        print(
            rep[
                [
                    "part",
                    "seconds",
                    "distance_before_mm",
                    "distance_registered_mm",
                    "distance_final_mean_mm",
                    "layers",
                    "iterations",
                ]
            ]
            .round(4)
            .to_string(index=False)
        )
    sj = scaled_jacobian(nodes, tpl.hexes)
    print(f"morphed mean: min scaled Jacobian {sj.min():.3f}, inverted {int((sj <= 0).sum())}")
    w = grid_weights(a.grid_modes, [-3, -2, -1, 0, 1, 2, 3]).astype(float)
    for method in ("nearest", "smooth"):
        h = transfer_fields(tpl, nodes, ssm, c.landmarks, a.grid_modes, method)
        t0 = time.perf_counter()
        stats = inverted_over_grid(h, tpl.hexes, w)
        dt = time.perf_counter() - t0
        print(
            f"{method:8s}: inverted elements {100 * stats['inverted_element_fraction']:.4f} %, models with any "
            f"{stats['models_with_inverted']} of {len(w)}; fused sample+check {len(w) * len(tpl.hexes) / dt / 1e6:.2f} "
            f"M elements/s"
        )
    import pyvista as pv

    grid = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: tpl.hexes}, nodes)
    reps = 20
    t0 = time.perf_counter()
    for _ in range(reps):
        grid.cell_quality("scaled_jacobian")
    t_vtk = (time.perf_counter() - t0) / reps
    x = np.ascontiguousarray(nodes[: tpl.n_hex_nodes])
    min_scaled_jacobian_nb(x, tpl.hexes)  # compile
    t0 = time.perf_counter()
    for _ in range(reps):
        min_scaled_jacobian_nb(x, tpl.hexes)
    t_nb = (time.perf_counter() - t0) / reps
    print(
        f"scaled Jacobian: numba {len(tpl.hexes) / t_nb / 1e6:.2f} M/s, vtkMeshQuality {len(tpl.hexes) / t_vtk / 1e6:.2f} "
        f"M/s, ratio {t_vtk / t_nb:.2f}"
    )
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        path = write_inp(fe_model(tpl, nodes), Path(d) / "Mean_Model (Template).inp")
        dt = time.perf_counter() - t0
        print(f".inp write: {dt:.2f} s, {path.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
