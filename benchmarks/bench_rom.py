"""Benchmark and full run of the FE validation: the ROM of one model for every configured extraction
(lumbar pelvis..T10, thoracic functional units) and load case, with solve times and peak memory per ccx run,
then the comparison with the in-vitro references (the same package calls as the rules rom_model and
rom_validation).

Run: python benchmarks/bench_rom.py [--config config/config.yaml] [--results results] [--out /tmp/rom_bench]
         [--model model_08403] [--threads 2]
Reads <results>/template/template.npz and the model's coordinates (<results>/models/<model>.inp if it
exists, else the hex SSM <results>/template/hex_ssm.npz sampled at the model's weights); writes the ROM
table, validation table, ALL-effect table and figure into --out, and prints per run: seconds, peak RSS (MB),
increments, and the totals.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import yaml


def model_points(results: Path, model: str, grid: dict, template) -> np.ndarray:
    from spinecohort.fe.export import read_deck_points
    from spinecohort.fe.models import hex_points_checked, parse_model_id
    from spinecohort.mesh.hex_ssm import HexSSM
    from spinecohort.store.zarr_store import weights_of

    deck = results / "models" / f"{model}.inp"
    if deck.exists():
        return read_deck_points(deck, template)
    i = parse_model_id(model, grid["n_modes"], grid["levels"])
    w = np.asarray(weights_of(i, grid["n_modes"], grid["levels"]), dtype=np.float64)
    pts, report = hex_points_checked(template, HexSSM.load(results / "template" / "hex_ssm.npz"), w)
    print(f"{model}: weights {w.tolist()} SD, Jacobian check {report}")
    return pts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--results", default=None, help="results folder (default: the config's)")
    ap.add_argument("--out", default="/tmp/spinecohort_bench_rom")
    ap.add_argument("--model", default=None, help="model_NNNNN (default: the config's rom.model)")
    ap.add_argument("--threads", type=int, default=None, help="parallel ccx runs (default: rom.threads)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(asctime)s %(message)s")

    from spinecohort.fe.materials import materials_from_config
    from spinecohort.figures.rom import validation_figure
    from spinecohort.mesh.template import HexTemplate
    from spinecohort.rom.compare import validate_from_config
    from spinecohort.rom.run import solve_model

    cfg = yaml.safe_load(Path(args.config).read_text())
    rom = dict(cfg["rom"])
    if args.threads:
        rom["threads"] = args.threads
    model = args.model or rom["model"]
    results = Path(args.results or cfg["results"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    template = HexTemplate.load(results / "template" / "template.npz")
    points = model_points(results, model, cfg["grid"], template)
    t0 = time.perf_counter()
    table = solve_model(template, points, rom, out / model, model, materials_from_config(cfg["fe"]))
    wall = time.perf_counter() - t0
    table.to_csv(out / f"{model}.csv", index=False)
    val = validate_from_config(table, rom)
    val.to_csv(out / "validation.csv", index=False)
    validation_figure(val, out / "validation.png", title=model)
    runs = table.drop_duplicates(["mode", "unit", "variant", "load_case"])
    print("\nper ccx run (s, peak RSS MB):")
    print(
        runs.groupby(["mode", "unit"])
        .agg(
            runs=("solve_s", "size"),
            total_s=("solve_s", "sum"),
            max_s=("solve_s", "max"),
            peak_mb=("peak_rss_mb", "max"),
        )
        .to_string()
    )
    print(
        f"\nwall time {wall:.1f} s with {rom['threads']} parallel ccx runs; sum of solve times "
        f"{runs['solve_s'].sum():.1f} s; peak RSS of one ccx run {runs['peak_rss_mb'].max():.0f} MB"
    )
    print("\nROM (deg):")
    print(table.pivot_table(index=["mode", "segment"], columns="load_case", values="rom_deg").round(2).to_string())
    print("\nvalidation:")
    print(
        val[
            ["segment", "motion", "side", "mode", "model_deg", "accept_low", "accept_high", "in_range", "in_range_seed"]
        ].to_string()
    )
    print(f"\nwritten to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
