"""Benchmark of the .inp export: write_inp, parse_template + substitute_coordinates, read_inp_nodes.

Run: python benchmarks/bench_abaqus.py [--sizes 100000 500000]
Prints seconds and MB/s per size, and the ratio to meshio's own Abaqus writer at the smallest size.
A structured hex block stands in for the template (about one hex per node, like the spine mesh).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from spinecohort.fe.abaqus import FEModel, LinearElastic, Section
from spinecohort.fe.inp_template import parse_template, read_inp_nodes, substitute_coordinates
from spinecohort.fe.writers import write_inp
from spinecohort.testing import hex_grid


def hex_block(n_nodes: int) -> FEModel:
    """A structured nx x nx x nz hex block with about n_nodes nodes (1 mm spacing) and two node sets."""
    nx = 20
    nz = max(2, round(n_nodes / (nx + 1) ** 2)) - 1
    xs, zs = np.arange(nx + 1.0), np.arange(nz + 1.0)
    nodes, hexes = hex_grid(xs, xs, zs, x_fastest=True)
    nodes += 0.123456789
    half = len(hexes) // 2
    return FEModel(
        nodes,
        {"BODY": ("C3D8", hexes)},
        node_sets={"BASE": np.flatnonzero(nodes[:, 2] < 1), "TOP": np.flatnonzero(nodes[:, 2] > nz - 0.5)},
        element_sets={"LOWER": np.arange(half), "UPPER": np.arange(half, len(hexes))},
        materials=[LinearElastic("BONE", 12000.0, 0.3)],
        sections=[Section("LOWER", "BONE"), Section("UPPER", "BONE")],
    )


def best_of(fn, repeats=3):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 500_000])
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for n in args.sizes:
            model = hex_block(n)
            path = tmp / f"block_{n}.inp"
            t_write, _ = best_of(lambda: write_inp(model, path))
            mb = path.stat().st_size / 1e6
            t_parse, tpl = best_of(lambda: parse_template(path))
            moved = model.nodes + rng.normal(0, 0.5, model.nodes.shape)
            out = tmp / "moved.inp"
            t_sub, _ = best_of(lambda: substitute_coordinates(tpl, moved, out))
            t_sub_path, _ = best_of(lambda: substitute_coordinates(path, moved, out))
            t_read, _ = best_of(lambda: read_inp_nodes(out))
            print(f"{len(model.nodes):>7d} nodes {model.n_elements:>7d} hexes  deck {mb:6.1f} MB")
            print(f"  write_inp                       {t_write:6.2f} s  {mb / t_write:6.1f} MB/s")
            print(f"  parse_template                  {t_parse:6.2f} s")
            print(f"  substitute_coordinates (parsed) {t_sub:6.2f} s  {mb / t_sub:6.1f} MB/s")
            print(f"  substitute_coordinates (path)   {t_sub_path:6.2f} s")
            print(f"  read_inp_nodes                  {t_read:6.2f} s")
        import meshio

        model = hex_block(args.sizes[0])
        mesh = meshio.Mesh(model.nodes, [("hexahedron", model.element_blocks["BODY"][1])])
        t_meshio, _ = best_of(lambda: meshio.write(tmp / "meshio.inp", mesh, file_format="abaqus"), repeats=1)
        t_ours, _ = best_of(lambda: write_inp(model, tmp / "ours.inp"), repeats=1)
        print(
            f"meshio.write abaqus at {len(model.nodes)} nodes: {t_meshio:.2f} s; write_inp {t_ours:.2f} s; "
            f"speed-up x{t_meshio / t_ours:.1f}"
        )


if __name__ == "__main__":
    main()
