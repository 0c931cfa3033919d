"""Benchmark: size and speed of the cohort store for one shard of realistic SSM samples.

    python benchmarks/bench_store.py [--resolutions coarse default] [--shard 24] [--shard-models 343]
                                     [--encodings int32-delta int32 float32] [--residual]

Realistic coordinates: a synthetic 42-patient cohort (coarse ~17k, default ~81k vertices per model) ->
Procrustes -> PCA -> SSM samples on the 5 x {-3..3} grid for the models of one shard.  The same shapes
fill tri/points and hex/points (no hex template needed), so each write stores 2 x models x nodes nodes.

Prints, per resolution and encoding: stored bytes per node (target <= 5; float32+zstd ~ 11), max decode
error, write_shard throughput (models/s, both arrays, including the decode check and checksums),
shard read and random single-model read throughput.  ``--residual`` adds the per-model residual
encoding (store mean + int residual, which plain zarr.open cannot turn into mm) for comparison.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import zarr

from spinecohort.cohort.synthetic import generate_cohort
from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.procrustes import procrustes_align
from spinecohort.store import zarr_store as S

warnings.filterwarnings("ignore", message="Numcodecs codecs are not in the Zarr")


def shard_bytes(path: Path, shard: int, array: str) -> int:
    return (path / array / "c" / str(shard) / "0" / "0").stat().st_size


def bench_encoding(
    shapes: np.ndarray, shard: int, shard_models: int, encoding: str, base: Path, residual_of: np.ndarray | None = None
) -> dict:
    m, n, _ = shapes.shape
    path = base / f"{encoding}{'-residual' if residual_of is not None else ''}.zarr"
    S.create_store(path, n, n, shard_models=shard_models, encoding=encoding)
    data = shapes if residual_of is None else shapes - residual_of
    t0 = time.perf_counter()
    S.write_shard(path, shard, data, data)
    t_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    back = S.read_shard(path, shard, "hex/points")
    t_read = time.perf_counter() - t0
    if residual_of is not None:
        back = back + residual_of
    err = float(np.abs(back - shapes).max())
    root = zarr.open(str(path), mode="r")
    start = S.shard_range(shard, shard_models)[0]
    picks = np.random.default_rng(0).integers(start, start + m, 20)
    t0 = time.perf_counter()
    for i in picks:
        root["hex/points"][int(i)]
    t_one = (time.perf_counter() - t0) / len(picks)
    nbytes = shard_bytes(path, shard, "tri/points") + shard_bytes(path, shard, "hex/points")
    return {
        "bytes_per_node": nbytes / (2 * m * n),
        "max_err_mm": err,
        "write_models_s": m / t_write,
        "read_models_s": m / t_read,
        "random_read_models_s": 1 / t_one,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--resolutions", nargs="+", default=["coarse", "default"])
    ap.add_argument("--shard", type=int, default=24, help="shard 24 = w1 = w2 = 0 SD")
    ap.add_argument("--shard-models", type=int, default=S.DEFAULT_SHARD_MODELS)
    ap.add_argument("--encodings", nargs="+", default=list(S.ENCODINGS))
    ap.add_argument("--residual", action="store_true")
    a = ap.parse_args()
    for res in a.resolutions:
        t0 = time.perf_counter()
        ssm = build_ssm(procrustes_align(generate_cohort(42, resolution=res).vertices).aligned)
        start, stop = S.shard_range(a.shard, a.shard_models, S.n_models())
        shapes = ssm.sample(S.weights_of(np.arange(start, stop)))
        m, n, _ = shapes.shape
        print(
            f"\n{res}: {m} models x {n} nodes, |x| <= {np.abs(shapes).max():.0f} mm "
            f"(SSM built in {time.perf_counter() - t0:.0f} s)"
        )
        print(
            f"{'encoding':<22s} {'B/node':>7s} {'max err mm':>11s} {'write models/s':>15s} "
            f"{'read models/s':>14s} {'1-model reads/s':>16s}"
        )
        rows = {}
        with tempfile.TemporaryDirectory() as d:
            runs = [(e, None) for e in a.encodings]
            if a.residual:
                runs.append(("int32-delta", ssm.mean))
            for enc, resid in runs:
                r = bench_encoding(shapes, a.shard, a.shard_models, enc, Path(d), resid)
                label = enc + ("+mean-residual" if resid is not None else "")
                rows[label] = r
                print(
                    f"{label:<22s} {r['bytes_per_node']:7.2f} {r['max_err_mm']:11.2e} "
                    f"{r['write_models_s']:15.1f} {r['read_models_s']:14.1f} {r['random_read_models_s']:16.1f}"
                )
        if "float32" in rows and "int32-delta" in rows:
            ratio = rows["float32"]["bytes_per_node"] / rows["int32-delta"]["bytes_per_node"]
            print(
                f"  int32-delta is {ratio:.2f}x smaller than float32+zstd; "
                f"target <= 5 B/node {'met' if rows['int32-delta']['bytes_per_node'] <= 5 else 'MISSED'}"
            )


if __name__ == "__main__":
    main()
