"""Benchmark of the virtual-cohort stage (init_store, sample_shard: one pass per shard) on the default config.

    python benchmarks/bench_cohort.py                      # the whole cohort (all shards + Descriptive_List)
    python benchmarks/bench_cohort.py --shards 0           # a few shards only (extrapolated to all)

(The store stage alone, against the codec floor and at a reduced shard size: benchmarks/bench_store.py.)

Runs ``snakemake -j2`` at the repository root (it continues from the finished upstream stages in
results/), then prints wall time, models/s per shard job, peak RSS per job (results/benchmarks/*.tsv),
stored bytes per node and the repair counts (results/shards/*.sample.json, *.quality.csv).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import yaml
import zarr

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shards", help="comma-separated shard numbers (default: the whole cohort)")
    ap.add_argument("--snakemake-args", default="", help='extra snakemake arguments, e.g. "--config ..."')
    args = ap.parse_args()
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    r = ROOT / cfg["results"]
    grid, store = cfg["grid"], cfg["store"]
    total = len(grid["levels"]) ** grid["n_modes"]
    n_sh = -(-total // store["shard_models"])
    shards = list(range(n_sh)) if not args.shards else [int(s) for s in args.shards.split(",")]
    rel = cfg["results"]  # snakemake matches targets relative to the working directory
    targets = (
        [f"{rel}/virtual_cohort.csv"] if not args.shards else [f"{rel}/shards/{s:05d}.sample.json" for s in shards]
    )
    # targets first: --rerun-triggers takes several values (mtime: do not redo the finished upstream stages
    # because of unrelated config edits)
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        *targets,
        "-j2",
        *args.snakemake_args.split(),
        "--rerun-triggers",
        "mtime",
    ]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        print(proc.stderr[-3000:])
        return proc.returncode

    rows = []
    for s in shards:
        name = f"{s:05d}"
        rec = json.loads((r / "shards" / f"{name}.sample.json").read_text())
        q = pd.read_csv(r / "shards" / f"{name}.quality.csv")
        bs = pd.read_csv(r / "benchmarks" / "sample_shard" / f"{name}.tsv", sep="\t").iloc[-1]
        n = rec["models"][1] - rec["models"][0]
        rows.append(
            {
                "shard": s,
                "models": n,
                "sample_s": bs["s"],
                "sample_models_per_s": n / bs["s"],
                "sample_rss_mb": bs["max_rss"],
                "quality_s": rec["quality_s"],  # check + repair + Table 3 rows, one pass
                "measure_s": rec["measure_s"],
                "write_s": rec["write_s"],
                "bytes": sum(v["bytes"] for k, v in rec["objects"].items() if "points" in k),
                "inverted": int((q["invalid_before"] > 0).sum()),
                "repaired": int(q["repaired"].sum()),
                "unrepaired": int((q["invalid_after"] > 0).sum()),
                "min_sj_after": q["min_sj_after"].min(),
            }
        )
    t = pd.DataFrame(rows)
    z = zarr.open_group(str(r / "cohort.zarr"), mode="r")
    attrs = dict(z.attrs)
    nodes = z["tri/points"].shape[1] + attrs["n_hex_nodes"]  # per model node, as the shard records count
    pd.set_option("display.width", 200)
    print(t.round(3).to_string(index=False))
    print(
        f"\nsnakemake -j2 wall time: {wall:.0f} s for {len(shards)} of {n_sh} shards "
        f"({t['models'].sum()} models, {nodes} nodes per model: tri {z['tri/points'].shape[1]} + hex "
        f"{attrs['n_hex_nodes']} ({z['hex/volume_points'].shape[1]} stored), encoding {attrs['encoding']})"
    )
    print(f"bytes per model node: {t['bytes'].sum() / (t['models'].sum() * nodes):.2f}")
    job_s = t["sample_s"].sum()
    print(
        f"sample_shard: {t['sample_models_per_s'].median():.1f} models/s (median), peak RSS "
        f"{t['sample_rss_mb'].max():.0f} MB"
    )
    print(
        f"repairs: {t['inverted'].sum()} models with inverted hexes, {t['repaired'].sum()} repaired, "
        f"{t['unrepaired'].sum()} unrepaired; check + repair + Table 3 time {t['quality_s'].sum():.0f} s of "
        f"{t['sample_s'].sum():.0f} s sampling"
    )
    print(
        f"whole cohort on 2 cores (extrapolated from these shards' job times, {-(-n_sh // 2)} rounds of 2 jobs): "
        f"{job_s / len(shards) * -(-n_sh // 2) / 60:.1f} min"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
