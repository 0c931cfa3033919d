"""Which models of the virtual-cohort grid fold, where, and whether the store's untangling repairs them, without
building the store: the shard job's sampling (hex SSM formula plus disc distraction), check and repair on the
chosen models only.

Run (after rule hex_ssm of a default run):
    python benchmarks/bench_store_repair.py --results results
    python benchmarks/bench_store_repair.py --results results --models 237 14714
Prints the grid's models with inverted hexes (scaled Jacobian <= 0) by the linear formula and after the disc
distraction, per element layer (level or disc, layer kind); then, for every inverted model (or those named), the
inverted hexes before repair with where they are, the repair's outcome (nodes moved, largest displacement mm, the
step that worked, s) and the totals the store's quality tables would hold.  The grid pass takes ~30 s; a repair
~5-20 s.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

from spinecohort.layout import Layout
from spinecohort.mesh.contact import resolve_contact
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.quality.kernels import scaled_jacobian_batch_nb
from spinecohort.mesh.repair import RepairError, prepare_untangle, untangle
from spinecohort.mesh.template import HexTemplate
from spinecohort.store.grid import model_name, weights_of


def layer_names(template: HexTemplate) -> list[str]:
    """Per element layer (the hexes between node layers k and k + 1): 'L5 body 0-0.25', 'L5-S1 disc 4/5' ..."""
    names = []
    for low, high in zip(template.layers[:-1], template.layers[1:]):
        if low["kind"] == "body" and high["kind"] == "body":
            names.append(f"{low['level']} body {low['t']:g}-{high['t']:g}")
        elif low["kind"] == "s1":
            names.append(f"{high.get('disc', 'S1')} S1 plate - disc")
        elif low["kind"] == "disc":
            names.append(f"{low['disc']} disc {low['k']}/{low['n']}")
        else:
            names.append(f"{high.get('disc', '?')} disc 0/{high.get('n', '?')} ({low['level']} endplate)")
    return names


def grid_check(hex_ssm: HexSSM, hexes: np.ndarray, n: int, weights: np.ndarray, chunk: int = 500):
    """(inverted hexes per model and element (S, E) bool by the linear formula, the same after the distraction,
    the distracted coordinates of the models inverted after it: {row: (n, 3) mm})."""
    mean = np.ascontiguousarray(hex_ssm.mean[:n])
    linear, distracted, points = [], [], {}
    for i in range(0, len(weights), chunk):
        v = np.ascontiguousarray(mean[None] + np.tensordot(weights[i : i + chunk], hex_ssm.fields[:, :n], axes=(1, 0)))
        linear.append(scaled_jacobian_batch_nb(v, hexes) <= 0)
        if hex_ssm.contact is not None:
            resolve_contact(None, v, hex_ssm.contact)
        inv = scaled_jacobian_batch_nb(v, hexes) <= 0
        distracted.append(inv)
        points.update({i + k: v[k].copy() for k in np.flatnonzero(inv.any(1))})
    return np.concatenate(linear), np.concatenate(distracted), points


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", default="results", help="results folder with template/ and hex_ssm.npz")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--models", nargs="*", type=int, help="model IDs to repair (default: every inverted one)")
    args = ap.parse_args()
    grid = yaml.safe_load(Path(args.config).read_text())["grid"]
    lay = Layout(args.results)
    template, hex_ssm = HexTemplate.load(lay.template), HexSSM.load(lay.hex_ssm)
    n, hexes = template.n_hex_nodes, np.ascontiguousarray(template.hexes, dtype=np.int64)
    n_models = len(grid["levels"]) ** grid["n_modes"]
    weights = weights_of(np.arange(n_models), grid["n_modes"], grid["levels"])
    t0 = time.perf_counter()
    linear, distracted, points = grid_check(hex_ssm, hexes, n, weights)
    per_layer = len(template.grid.quads)
    names = layer_names(template)
    print(f"grid of {n_models} models checked in {time.perf_counter() - t0:.0f} s")
    for what, inv in (("linear formula", linear), ("after the disc distraction", distracted)):
        layers = inv.reshape(len(inv), -1, per_layer)
        print(f"{what}: {int(inv.any(1).sum())} models with {int(inv.sum())} inverted hexes")
        for k in np.flatnonzero(layers.any(axis=(0, 2))):
            print(f"   {names[k]:<30} {int(layers[:, k].sum()):>6} hexes in {int(layers[:, k].any(1).sum()):>4} models")
    chosen = sorted(points) if args.models is None else [m for m in args.models if m in points]
    ctx = prepare_untangle(hexes, np.ascontiguousarray(hex_ssm.mean[:n]))
    repaired, left, t_repair = 0, 0, 0.0
    for m in chosen:
        bad = np.flatnonzero(distracted[m])
        where = sorted({names[e // per_layer] for e in bad})
        t1 = time.perf_counter()
        try:
            _, rep = untangle(points[m], hexes, hex_ssm.mean[:n], context=ctx)
            outcome = (
                f"repaired: {rep.n_nodes_moved} nodes moved, largest {rep.max_displacement_mm:.2f} mm, "
                f"rings {rep.patch_rings}, last step {rep.attempts[-1].split(':')[0]}"
            )
            repaired += 1
        except RepairError as err:
            outcome, left = f"NOT repaired: {str(err)[:200]}", left + len(bad)
        dt = time.perf_counter() - t1
        t_repair += dt
        label = f"{model_name(m)} (weights {weights[m].astype(int).tolist()} SD)"
        print(f"{label}: {len(bad)} inverted in {where}; {outcome} ({dt:.1f} s)")
    print(f"{repaired} of {len(chosen)} models repaired in {t_repair:.0f} s; {left} inverted hexes left unrepaired")


if __name__ == "__main__":
    main()
