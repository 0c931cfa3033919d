"""Release throughput: the store zip, BagIt hashing, verification (crc32c of every shard object in the zip,
first and last model read), and what compressing the store would gain.

    .venv/bin/python benchmarks/bench_release.py [--store results/cohort.zarr] [--models 2401]

With an existing store (the pipeline's) it packs that; otherwise it writes a synthetic store of --models
random-walk models (20k + 20k nodes, zarr's real codec chain) in a temporary directory.  Prints seconds and
MB/s per step, the whole-release time extrapolated to the default store (8.7 GB), and the size ratio and
speed of zlib-6 and xz-6 on 64 MB of the store zip (why its members are stored, not deflated).
"""

from __future__ import annotations

import argparse
import lzma
import shutil
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
import yaml

from spinecohort.release import build_release, store_files
from spinecohort.store.zarr_store import create_store, n_shards, write_shard

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_STORE_GB = 8.7


def synthetic_store(path: Path, n_models: int, shard_models: int = 343, n_nodes: int = 20_000) -> Path:
    """A store of random-walk shapes (mm): neighbouring nodes close, as in the meshes."""
    n_modes = int(round(np.log(n_models) / np.log(7)))
    create_store(path, n_nodes, n_nodes, n_modes=n_modes, shard_models=shard_models)
    rng = np.random.default_rng(0)
    base = np.cumsum(rng.normal(0, 0.5, (n_nodes, 3)), axis=0).astype(np.float32)
    total = 7**n_modes
    for s in range(n_shards(total, shard_models)):
        m = min(shard_models, total - s * shard_models)
        pts = (
            base
            + rng.normal(0, 2.0, (m, 1, 3)).astype(np.float32)
            + rng.normal(0, 0.05, (m, n_nodes, 3)).astype(np.float32)
        )
        write_shard(path, s, pts, pts)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", type=Path, default=ROOT / "results" / "cohort.zarr")
    ap.add_argument("--models", type=int, default=2401, help="synthetic store size (7^k models)")
    ap.add_argument("--processes", type=int, default=2)
    args = ap.parse_args()
    meta = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["release"]
    with tempfile.TemporaryDirectory(prefix="bench-release-") as tmp:
        tmp = Path(tmp)
        store = args.store
        if not (store / "zarr.json").is_file():
            t0 = time.perf_counter()
            store = synthetic_store(tmp / "cohort.zarr", args.models)
            print(f"synthetic store: {args.models} models in {time.perf_counter() - t0:.1f} s")
        files = store_files(store)
        mb = sum((store / f).stat().st_size for f in files) / 1e6
        print(f"store {store}: {mb:.0f} MB in {len(files)} files -> one store zip")
        import zarr

        z = zarr.open_group(str(store), mode="r")
        counts = {
            "n_models": int(z.attrs["n_models"]),
            "shard_models": int(z.attrs["shard_models"]),
            "chunk_models": int(z.attrs["chunk_models"]),
            "levels": list(z.attrs["levels"]),
            "n_tri_nodes": 0,
            "n_hex_nodes": 0,
            "n_patients": 0,
            "n_personalized": 0,
            "n_modes": int(z.attrs["n_modes"]),
            "hex_type": "C3D8",
            "mean_model_id": None,
            "n_hex_elements": 0,
            "n_nodes_stored": 0,
            "error_bound_mm": 0.0,
        }
        rep = build_release(tmp / "release", store=store, files={}, meta=meta, counts=counts, processes=args.processes)
        total = rep["seconds"]
        print(f"store zip + payload: {rep['seconds_payload']:6.1f} s  {mb / rep['seconds_payload']:7.0f} MB/s")
        print(f"bagit (sha256):     {rep['seconds_bag']:6.1f} s  {mb / rep['seconds_bag']:7.0f} MB/s")
        print(
            f"verify (bagit + shard crc32c in the zip): {rep['seconds_verify']:6.1f} s  "
            f"{mb / rep['seconds_verify']:7.0f} MB/s"
        )
        print(
            f"whole release: {total:.1f} s, {mb / total:.0f} MB/s -> default store ({DEFAULT_STORE_GB} GB): "
            f"~{DEFAULT_STORE_GB * 1e3 / (mb / total) / 60:.1f} min"
        )
        with (tmp / "release" / "data" / "cohort.zarr.zip").open("rb") as f:
            sample = f.read(64 << 20)
        for name, fn in (("zlib-6", lambda b: zlib.compress(b, 6)), ("xz-6", lambda b: lzma.compress(b, preset=6))):
            t0 = time.perf_counter()
            n = len(fn(sample))
            dt = time.perf_counter() - t0
            print(
                f"{name} on {len(sample) / 1e6:.0f} MB of the store zip: size ratio {n / len(sample):.3f}, "
                f"{len(sample) / 1e6 / dt:.1f} MB/s (8.7 GB: ~{DEFAULT_STORE_GB * 1e3 / (len(sample) / 1e6 / dt) / 60:.0f} min)"
            )
        shutil.rmtree(tmp / "release")


if __name__ == "__main__":
    main()
