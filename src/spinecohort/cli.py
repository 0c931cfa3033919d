"""Command-line entry point ``spinecohort``: the package's functions without Snakemake."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np


def _generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .cohort import write_cohort_folder
    from .synthetic import generate_cohort

    bar = tqdm(total=args.n, desc="patients", unit="patient", disable=args.quiet)

    def progress(done, total):
        bar.update(done - bar.n)

    c = generate_cohort(args.n, seed=args.seed, resolution=args.resolution, noise_mm=args.noise_mm, progress=progress)
    bar.close()
    write_cohort_folder(args.out, c.ids, c.vertices, c.faces, c.landmarks, c.table)
    print(f"{len(c.ids)} patients ({c.n_candidates} candidates drawn), {c.vertices.shape[1]} vertices each -> {args.out}")
    return 0


def _check(args: argparse.Namespace) -> int:
    from .cohort import load_cohort

    folder = Path(args.folder)
    stls = sorted(folder.glob("*.stl"))
    c = load_cohort(stls, args.sheet or folder / "patients.csv", args.landmarks or folder / "landmarks.json",
                    units=args.units)
    ext = c.points.max(1) - c.points.min(1)
    print(f"{len(c.ids)} patients, {c.points.shape[1]} vertices, {len(c.faces)} triangles, in correspondence")
    print(f"extent (mm): {np.round(ext.mean(0), 1)} on average; sheet columns: {', '.join(c.table.columns)}")
    return 0


def _ssm_info(args: argparse.Namespace) -> int:
    from .pca import SSM

    ssm = SSM.load(args.ssm)
    print(f"{ssm.n_train} training shapes, {ssm.mean.shape[0]} vertices, {ssm.n_modes} modes")
    for t in (0.8, 0.9, 0.95, 0.99):
        print(f"  {100 * t:.0f} % of the variance: {ssm.modes_for_variance(t)} modes")
    sd = np.sqrt(ssm.eigenvalues[:10])
    print("  SD of the first modes (mm, RMS per vertex): " + ", ".join(f"{s / np.sqrt(ssm.mean.shape[0]):.2f}" for s in sd))
    return 0


def _export(args: argparse.Namespace) -> int:
    import yaml

    from .cohort import load_cohort_npz
    from .hex_ssm import HexSSM
    from .hex_template import HexTemplate
    from .models import virtual_model, write_model
    from .pca import SSM

    cfg = yaml.safe_load(Path(args.config).read_text())
    r = Path(args.results or cfg["results"])
    grid = cfg["grid"]
    template = HexTemplate.load(r / "template" / "template.npz")
    vm = virtual_model(args.model_id, SSM.load(r / "ssm" / "ssm.npz"), HexSSM.load(r / "template" / "hex_ssm.npz"),
                       template, grid["n_modes"], grid["levels"])
    out = args.out or Path(f"model_{vm.model_id:05d}.{args.format}")
    write_model(vm, args.format, out, template, load_cohort_npz(r / "cohort" / "cohort.npz").faces,
                cfg["template"]["hex_type"])
    print(f"model_{vm.model_id:05d} (weights {vm.weights.tolist()} SD) -> {out}; Jacobian check: {vm.repair}")
    return 0


def _query(args: argparse.Namespace) -> int:
    import pandas as pd
    import yaml

    from .tables import parse_range, query_models

    filters = args.filters
    if len(filters) % 2 or not all(f.startswith("--") for f in filters[::2]):
        raise ValueError(f"query filters must be pairs '--PARAM lo:hi', got {' '.join(filters)}")
    ranges = {k[2:]: parse_range(v, k[2:]) for k, v in zip(filters[::2], filters[1::2])}
    r = Path(args.results) if args.results else Path(yaml.safe_load(Path(args.config).read_text())["results"])
    csv = r / "virtual_cohort.csv"
    if not csv.is_file():
        raise ValueError(f"{csv} does not exist; run the pipeline (snakemake) first")
    ids = query_models(pd.read_csv(csv), ranges)
    print("\n".join(ids))
    print(f"{len(ids)} models match", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spinecohort", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate-cohort", help="write a synthetic patient cohort (STL folder + sheet + landmarks)")
    g.add_argument("out", type=Path)
    g.add_argument("--n", type=int, default=42, help="number of patients (default 42)")
    g.add_argument("--seed", type=int, default=20240549)
    g.add_argument("--resolution", choices=["coarse", "default", "fine"], default="default")
    g.add_argument("--noise-mm", type=float, default=0.8)
    g.add_argument("--quiet", action="store_true")
    g.set_defaults(func=_generate)

    c = sub.add_parser("check-cohort", help="validate a folder of patient STLs in correspondence")
    c.add_argument("folder", type=Path)
    c.add_argument("--sheet", type=Path)
    c.add_argument("--landmarks", type=Path)
    c.add_argument("--units", choices=["mm", "cm", "m"], default="mm")
    c.set_defaults(func=_check)

    s = sub.add_parser("ssm-info", help="summarise an ssm.npz (modes, compactness)")
    s.add_argument("ssm", type=Path)
    s.set_defaults(func=_ssm_info)

    e = sub.add_parser("export", help="materialize one virtual model (.inp, .stl or .vtu)")
    e.add_argument("model_id", help="model_08403 or 8403")
    e.add_argument("--format", choices=["inp", "stl", "vtu"], default="inp")
    e.add_argument("--out", type=Path)
    e.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    e.add_argument("--results", type=Path, help="results folder (default: the config's)")
    e.set_defaults(func=_export)

    q = sub.add_parser("query", help="model IDs of the virtual cohort with parameters in ranges, "
                                     "e.g. query --PI 50:60 --PT 25: (bounds inclusive, deg / mm)")
    q.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    q.add_argument("--results", type=Path, help="results folder (default: the config's)")
    q.set_defaults(func=_query)

    args, extra = parser.parse_known_args(argv)
    if extra and args.command != "query":
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.filters = extra
    logging.basicConfig(level=logging.WARNING)
    try:
        return args.func(args)
    except ValueError as exc:  # input errors carry the file and the problem: print them, not a traceback
        print(f"spinecohort: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
