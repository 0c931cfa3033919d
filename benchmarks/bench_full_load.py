"""Benchmark: the whole-model pure-moment decks exactly as ``spinecohort export --format inp --load <case>`` writes
them, solved by ccx at the full moment, per model and load case.

Run: python benchmarks/bench_full_load.py [--config config/config.yaml] [--results results]
         [--models model_08403 model_00000 model_16806] [--cases flexion extension ...] [--moment-nm 7.5]
         [--threads 2] [--timeout-s 1800] [--guided] [--out /tmp/spinecohort_bench_full_load]
One ccx at a time.  Prints per model and load case: the load fraction reached (1 = the full moment), T1's
rotation about the load's axis (degrees, the ROT NODE's rotation vector projected on the deck's load axis), the
moment on T1 about that axis over the load (1: in equilibrium) and the moment across it that held a guided T1 on
it (N.mm, from the forces T1's rigid nodes pass to the spine; ~0 free), the wall time (s) and the converged
increments; a run stopped by --timeout-s keeps what it reached.  Writes the
table to <out>/full_load.csv.  Default models: the mean and the all -3 SD / all +3 SD corners of the grid.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

CASES = ("flexion", "extension", "lateral_left", "lateral_right", "axial_left", "axial_right")


def corner_models(grid: dict) -> list[str]:
    """The mean model (every weight 0) and the all -3 SD / all +3 SD corners of the weight grid."""
    from spinecohort.store.grid import model_id, model_name

    levels = np.asarray(grid["levels"], dtype=np.float64)
    n = int(grid["n_modes"])
    return [model_name(model_id(np.full(n, w), levels)) for w in (0.0, levels.min(), levels.max())]


def converged_increments(sta: Path) -> int:
    """Increments ccx finished (the .sta file's rows without a 'U' = not converged attempt)."""
    if not sta.exists():
        return 0
    rows = [r.split() for r in sta.read_text().splitlines()]
    return sum(1 for r in rows if len(r) >= 7 and r[0].isdigit() and not r[2].endswith("U"))


def solve(deck: Path, workdir: Path, threads: int, timeout_s: float) -> dict:
    """Run ccx on one exported load deck; what it reached even if it stopped short."""
    from spinecohort.fe.calculix import CalculixError, parse_dat, run_ccx

    t0 = time.perf_counter()
    try:
        run_ccx(deck, workdir, threads=threads, timeout_s=timeout_s)
        status = "converged"
    except CalculixError as exc:
        status = "timeout" if "timed out" in str(exc) else "stopped: " + str(exc).splitlines()[-1][:80]
    seconds = time.perf_counter() - t0
    dat = workdir / f"{deck.stem}.dat"
    rot = [b for b in parse_dat(dat.read_text()) if b.node_set.upper() == "ROTTOP"] if dat.exists() else []
    return {
        "status": status,
        "seconds": round(seconds, 1),
        "increments": converged_increments(workdir / f"{deck.stem}.sta"),
        "load_fraction": rot[-1].time if rot else 0.0,
        "rotation_rad": rot[-1].values[0] if rot else np.zeros(3),
    }


def moment_on_t1(deck_text: str, dat: Path, axis: np.ndarray, moment_nmm: float) -> tuple[float, np.ndarray]:
    """At the last printed increment: the moment on T1 about the load's axis as a fraction of the load applied then
    (1 = equilibrium), and the moment (N.mm, global) across the axis that held a guided T1 on it (~0 free)
    (`spinecohort.rom.reaction.moment_on_top`).  NaN when nothing was printed."""
    from spinecohort.fe.calculix import parse_dat
    from spinecohort.rom.reaction import moment_on_top
    from spinecohort.rom.run import guide_moment

    tops = moment_on_top(deck_text, parse_dat(dat.read_text())) if dat.exists() else []
    if not tops:
        return np.nan, np.full(3, np.nan)
    load = tops[-1].time * moment_nmm
    return float(tops[-1].moment_nmm @ axis) / load, guide_moment(tops[-1].moment_nmm, load * axis)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--results", default=None, help="results folder (default: the config's)")
    ap.add_argument("--models", nargs="*", default=None, help="default: the mean and the -3 / +3 SD corners")
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    ap.add_argument("--moment-nm", type=float, default=7.5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--timeout-s", type=float, default=1800.0, help="per ccx run")
    ap.add_argument("--guided", action="store_true", help="export --guided: the top turns about the load's axis only")
    ap.add_argument("--out", default="/tmp/spinecohort_bench_full_load")
    args = ap.parse_args(argv)

    from spinecohort.cli import main as cli
    from spinecohort.fe.pure_moment import load_axis

    cfg = yaml.safe_load(Path(args.config).read_text())
    results = args.results or cfg.get("results", "results")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for model in args.models or corner_models(cfg["grid"]):
        for case in args.cases:
            deck = out / f"{model}_{case}.inp"
            export = ["export", model, "--format", "inp", "--load", case, "--moment-nm", str(args.moment_nm)]
            export += ["--guided"] if args.guided else []
            cli([*export, "--config", args.config, "--results", str(results), "--out", str(deck)])
            work = out / f"{model}_{case}"
            run = solve(deck, work, args.threads, args.timeout_s)
            text = deck.read_text()
            axis = load_axis(text)
            balance, guide = moment_on_t1(text, work / f"{deck.stem}.dat", axis, 1000 * args.moment_nm)
            row = {
                "model": model,
                "case": case,
                "guided": args.guided,
                "load_fraction": round(float(run["load_fraction"]), 4),
                "t1_rotation_deg": round(float(np.degrees(run["rotation_rad"] @ axis)), 2),
                "moment_balance": round(balance, 4),
                "guide_moment_nmm": round(float(np.linalg.norm(guide)), 1),
                "seconds": run["seconds"],
                "increments": run["increments"],
                "status": run["status"],
            }
            rows.append(row)
            print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    table = pd.DataFrame(rows)
    table.to_csv(out / "full_load.csv", index=False)
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
