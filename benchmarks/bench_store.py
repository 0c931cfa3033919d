"""Benchmark of the virtual-cohort store stage: init -> shard jobs -> check_store, against the codec floor.

    python benchmarks/bench_store.py [--results results] [--shard-models 343] [--shards 0 24 48]
                                     [--explore] [--explore-models 49]

Needs the inputs of the shard jobs of a default-config run (``snakemake -j2 results/template/hex_ssm.npz``:
ssm, hex SSM, template, cohort under ``--results``).  Writes a fresh store in a temporary folder with the
default grid (7^5 = 16,807 models) cut into shards of ``--shard-models``, runs the listed shards each as its
own process (the ``sample_shard`` job's code, ``store.shards.run_shard_job``), then ``check_store``, and prints:

* per job: wall, CPU (user + system, from ``wait4``), peak RSS, models/s, stored bytes per node;
* the **compression floor**: CPU time to encode the same stored values with the same codec chain
  (transpose + blosc bitshuffle zstd) and nothing else, measured in this run, and the stage's CPU / floor;
* a cold read of one model's tri + hex coordinates (the shard files dropped from the page cache with
  ``posix_fadvise(DONTNEED)``, fresh process), and the same model read by tensorstore (a second Zarr v3
  implementation) compared with zarr-python's;
* the extrapolation to the default 16,807 models in shards of ``store.shard_models`` on 2 cores.

``--explore``: bytes per node and encode speed of the alternative layouts and codecs (core Zarr v3 codecs
only) on the first ``--explore-models`` models of the first listed shard (docs/store.md).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from spinecohort.layout import Layout
from spinecohort.store import zarr_store as S

ROOT = Path(__file__).resolve().parents[1]

_JOB = """
import json, sys
from spinecohort.store.shards import run_shard_job
a = json.loads(sys.argv[1])
rec = run_shard_job(a["store"], a["shard"], a["inputs"], a["outputs"], a["settings"], a["measure"])
"""
_CHECK = """
import sys
from spinecohort.store.zarr_store import shard_problems
print(len(shard_problems(sys.argv[1])))
"""
_READ = """
import sys, time
t0 = time.perf_counter()
import zarr
t1 = time.perf_counter()
z = zarr.open(sys.argv[1], mode="r")
i = int(sys.argv[2])
tri, hexp = z["tri/points"][i], z["hex/points"][i]
print(time.perf_counter() - t1, t1 - t0, tri.shape[0], hexp.shape[0])
"""


#: what Snakemake sets for a job with threads: 1 (snakemake.shell)
ONE_THREAD = {
    k: "1"
    for k in ("OMP_NUM_THREADS", "GOTO_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")
}


def run(cmd: list[str]) -> dict:
    """Run a process as a threads: 1 job; its wall time, CPU time (user + system) and peak RSS from wait4."""
    t0 = time.perf_counter()
    env = {**os.environ, **ONE_THREAD}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    out, err = proc.stdout.read(), proc.stderr.read()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd[:3]} failed ({proc.returncode}): {err[-2000:]}")
    return {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "rss_mb": ru.ru_maxrss / 1024, "out": out}


def codec_floor(path: Path, shards: list[int]) -> float:
    """CPU s to encode the stored values of ``shards`` with the store's codec chain alone."""
    import zarr
    from numcodecs import blosc

    blosc.set_nthreads(1)  # as in the shard job
    root = zarr.open_group(str(path), mode="r")
    meta = dict(root.attrs)
    codec = S._blosc_codecs(root["tri/points"].metadata.codecs[0].codecs[-1].clevel)[1]
    cm = meta["chunk_models"]
    cpu = 0.0
    for s in shards:
        a, b = S.shard_range(s, meta["shard_models"], meta["n_models"])
        for name in S.POINT_ARRAYS:
            x = root[name][a:b]  # decoded once, outside the timing
            t0 = time.process_time()
            for i in range(0, len(x), cm):
                codec.encode(np.ascontiguousarray(x[i : i + cm].transpose(S.CHUNK_ORDER)))
            cpu += time.process_time() - t0
    return cpu


def drop_from_page_cache(files) -> None:
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def explore(results: Layout, shard: int, shard_models: int, n: int) -> None:
    """B/node and encode MB/s of alternative core-codec layouts on n models of ``shard``."""
    from numcodecs import Blosc, Zstd

    from spinecohort.mesh.hex_ssm import HexSSM
    from spinecohort.ssm.model import SSM
    from spinecohort.store.shards import sample_points

    a, _ = S.shard_range(shard, shard_models)
    w = S.weights_of(np.arange(a, a + n))
    tri, hexp = sample_points(SSM.load(results.ssm), HexSSM.load(results.hex_ssm), w)
    x64 = [tri.astype(np.float64), hexp.astype(np.float64)]
    reps = {
        "float32 mm / 2^-10": [S.quantize_mm(x) for x in x64],
        "float32 mm / 2^-9": [(np.rint(x * 512) / 512).astype(np.float32) for x in x64],
        "float32 mm, unrounded": [x.astype(np.float32) for x in x64],
        "int32 um (needs CF decoding)": [np.rint(x * 1000).astype(np.int32) for x in x64],
    }
    bit, byte = Blosc.BITSHUFFLE, Blosc.SHUFFLE
    variants = [
        ("float32 mm / 2^-10", 1, (0, 2, 1), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 1, (0, 2, 1), Blosc("zstd", 3, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 7, (2, 0, 1), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 7, (2, 1, 0), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 7, (2, 1, 0), Blosc("zstd", 2, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 7, (2, 1, 0), Blosc("zstd", 3, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 7, (2, 1, 0), Blosc("zstd", 1, byte, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 7, (2, 1, 0), Blosc("zstd", 1, bit, 0)),
        ("float32 mm / 2^-10", 7, (2, 1, 0), Zstd(3)),
        ("float32 mm / 2^-10", 49, (2, 1, 0), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-10", 49, (2, 1, 0), Blosc("zstd", 3, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm / 2^-9", 7, (2, 1, 0), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
        ("float32 mm, unrounded", 7, (2, 1, 0), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
        ("int32 um (needs CF decoding)", 1, (0, 2, 1), Blosc("zstd", 3, bit, S.BLOSC_BLOCK_BYTES)),
        ("int32 um (needs CF decoding)", 7, (2, 1, 0), Blosc("zstd", 1, bit, S.BLOSC_BLOCK_BYTES)),
    ]
    print(f"\nExplore: {n} models of shard {shard} ({tri.shape[1]} tri + {hexp.shape[1]} hex nodes), core codecs only")
    print(f"{'values':<30s} {'models/chunk':>12s} {'stored order':>14s} {'codec':<34s} {'B/node':>7s} {'enc MB/s':>9s}")
    for rep, per, order, codec in variants:
        nbytes = raw = 0
        cpu = 0.0
        for q in reps[rep]:
            for i in range(0, len(q), per):
                c = np.ascontiguousarray(q[i : i + per].transpose(order))
                t0 = time.process_time()
                nbytes += len(codec.encode(c))
                cpu += time.process_time() - t0
                raw += c.nbytes
        nodes = n * (tri.shape[1] + hexp.shape[1])
        axes = "".join("mnc"[k] for k in order)  # m model, n node, c coordinate; outermost first
        cfg = codec.get_config()
        name = (
            f"blosc {['no', 'byte', 'bit'][cfg['shuffle']]}shuffle zstd {cfg['clevel']} bs={cfg['blocksize'] >> 10}k"
            if cfg["id"] == "blosc"
            else f"zstd {cfg['level']}"
        )
        print(f"{rep:<30s} {per:>12d} {axes:>14s} {name:<34s} {nbytes / nodes:7.2f} {raw / max(cpu, 1e-9) / 1e6:9.0f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results", help="results folder of a default-config run (inputs)")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--shard-models", type=int, default=343, help="models per shard in this benchmark")
    ap.add_argument("--shards", type=int, nargs="+", default=[0, 24, 48])
    ap.add_argument("--explore", action="store_true")
    ap.add_argument("--explore-models", type=int, default=49)
    a = ap.parse_args(argv)
    cfg = yaml.safe_load(Path(a.config).read_text())
    L = Layout(a.results)
    inputs = {"ssm": L.ssm, "hex_ssm": L.hex_ssm, "template": L.template, "cohort": L.cohort}
    for k, v in inputs.items():
        if not Path(v).is_file():
            raise SystemExit(f"{v} missing: run `snakemake -j2 {L.hex_ssm}` on the default config first ({k})")
    grid = cfg["grid"]
    total = S.n_models(grid["n_modes"], grid["levels"])
    with tempfile.TemporaryDirectory(prefix="bench-store-") as tmp:
        store = Path(tmp) / "cohort.zarr"
        t0, c0 = time.perf_counter(), time.process_time()
        with np.load(L.ssm) as z:
            n_tri = z["mean"].shape[0]
        with np.load(L.hex_ssm) as z:
            n_hex = z["mean"].shape[0]
        S.create_store(
            store, n_tri, n_hex, grid["n_modes"], grid["levels"], a.shard_models, {}, cfg["store"]["encoding"]
        )
        init = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
        print(
            f"store: {total} models x ({n_tri} tri + {n_hex} hex nodes), shards of {a.shard_models}; init {init['wall_s']:.2f} s"
        )
        print(
            f"{'shard':>5s} {'models':>6s} {'wall s':>7s} {'CPU s':>7s} {'RSS MB':>7s} {'models/s':>8s} {'B/node':>7s} {'enc CPU s':>9s}  phases (s)"
        )
        jobs, records = [], []
        for s in a.shards:
            outs = {k: str(Path(tmp) / f"{s:05d}.{k}") for k in ("quality", "params", "tri_vs_hex", "record")}
            arg = dict(
                store=str(store), shard=s, inputs=inputs, outputs=outs, settings=cfg["store"], measure=cfg["measure"]
            )
            r = run([sys.executable, "-c", _JOB, json.dumps(arg)])
            rec = json.loads(Path(outs["record"]).read_text())
            jobs.append(r)
            records.append(rec)
            n = rec["models"][1] - rec["models"][0]
            phases = {
                k[:-2]: round(rec[k], 1)
                for k in ("load_s", "sample_s", "check_repair_s", "table3_s", "measure_s", "write_s", "close_s")
            }
            print(
                f"{s:>5d} {n:>6d} {r['wall_s']:7.1f} {r['cpu_s']:7.1f} {r['rss_mb']:7.0f} {n / r['wall_s']:8.1f} "
                f"{rec['stored_bytes'] / rec['stored_nodes']:7.2f} {rec['encode_cpu_s']:9.2f}  {phases}"
            )
        chk = run([sys.executable, "-c", _CHECK, str(store)])
        bad = int(chk["out"].strip())
        print(
            f"check_store: {chk['wall_s']:.1f} s wall, {chk['cpu_s']:.1f} s CPU, {bad} shards flagged (unwritten ones)"
        )
        floor = codec_floor(store, a.shards)
        models = sum(r["models"][1] - r["models"][0] for r in records)
        stage_cpu = init["cpu_s"] + sum(j["cpu_s"] for j in jobs) + chk["cpu_s"]
        stage_wall = init["wall_s"] + sum(j["wall_s"] for j in jobs) + chk["wall_s"]
        nbytes = sum(r["stored_bytes"] for r in records)
        nodes = sum(r["stored_nodes"] for r in records)
        print(
            f"\nstage (init + {len(jobs)} shard jobs + check, sequential): {stage_wall:.1f} s wall, {stage_cpu:.1f} s CPU for "
            f"{models} models; codec floor {floor:.2f} s CPU (jobs' own encode CPU {sum(r['encode_cpu_s'] for r in records):.2f} s)"
            f" -> CPU / floor = {stage_cpu / floor:.1f} (goal <= 1.5)"
        )
        print(
            f"peak RSS per job: {max(j['rss_mb'] for j in jobs):.0f} MB (goal <= 1500); {nbytes / nodes:.2f} B/node (goal <= 5)"
        )
        # cold read of one model: the middle model of the first shard
        i = records[0]["models"][0] + (records[0]["models"][1] - records[0]["models"][0]) // 2
        drop_from_page_cache([store / o for o in records[0]["objects"]])
        cold = run([sys.executable, "-c", _READ, str(store), str(i)])
        warm = run([sys.executable, "-c", _READ, str(store), str(i)])
        (c_read, c_imp), w_read = map(float, cold["out"].split()[:2]), float(warm["out"].split()[0])
        print(
            f"read model {i} (tri + hex) in a fresh process, zarr.open + 2 reads: cold {c_read:.3f} s, warm {w_read:.3f} s "
            f"(goal cold <= 0.1 s; `import zarr` itself: {c_imp:.2f} s)"
        )
        try:
            import tensorstore as ts
            import zarr

            z = zarr.open(str(store), mode="r")
            same = all(
                np.array_equal(
                    ts.open({"driver": "zarr3", "kvstore": {"driver": "file", "path": str(store / arr)}})
                    .result()[i]
                    .read()
                    .result(),
                    z[arr][i],
                )
                for arr in S.POINT_ARRAYS
            )
            print(f"tensorstore reads model {i}: {'identical to zarr-python' if same else 'DIFFERENT'}")
        except ImportError:
            print("tensorstore not installed (pip install -e '.[test]')")
        # extrapolation: the default run's shard size, 2 cores. From CPU time (what a job takes on a quiet
        # machine: single-threaded, its wall is its CPU) and from this run's wall time (inflated by the load)
        sm = cfg["store"]["shard_models"]
        n_sh = S.n_shards(total, sm)
        rounds = math.ceil(n_sh / 2)
        start_up = float(np.median([r["load_s"] for r in records]))
        load = os.getloadavg()[0]
        for basis, spent, check in (("CPU", "cpu_s", chk["cpu_s"]), ("wall", "wall_s", chk["wall_s"])):
            per_model = (sum(j[spent] for j in jobs) - start_up * len(jobs)) / models
            job_s = start_up + sm * per_model
            check_s = check * n_sh * sm / models  # hashing scales with the bytes
            est = init["wall_s"] + rounds * job_s + check_s
            print(
                f"extrapolated ({basis} time{f', load average {load:.1f}' if basis == 'wall' else ''}) to {total} "
                f"models in {n_sh} shards of {sm} on 2 cores: {per_model * 1e3:.1f} ms/model -> {job_s:.0f} s per job, "
                f"{rounds} rounds, check ~{check_s:.0f} s: store stage ~{est / 60:.1f} min (goal <= 5 min)"
            )
        print(f"store size ~{nbytes / nodes * total * (n_tri + n_hex) / 1e9:.1f} GB")
    if a.explore:
        explore(L, a.shards[0], a.shard_models, a.explore_models)
    return 0


if __name__ == "__main__":
    sys.exit(main())
