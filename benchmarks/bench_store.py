"""Benchmark of the virtual-cohort store stage: init -> shard jobs -> check_store, against the codec floor.

    python benchmarks/bench_store.py [--results results] [--out DIR] [--shard-models 343] [--shards 0 24 48]
                                     [--all] [--jobs 2]
    python benchmarks/bench_store.py --results results --all --jobs 2    # the store stage as the config cuts it

Needs the inputs of the shard jobs of a default-config run (``snakemake -j2 results/template/hex_ssm.npz``:
ssm, hex SSM, template, cohort under ``--results``).  Writes a fresh store (in a temporary folder under
``--out``, removed at the end) with the default grid (7^5 = 16,807 models) cut into shards of
``--shard-models`` (with ``--all`` by default the config's ``store.shard_models``, else 343), runs the listed
shards (``--all``: every shard, i.e. the whole store stage) each as its own process with Snakemake's
one-thread environment, ``--jobs`` at a time (the ``sample_shard`` job's code,
``virtual.shard_job.run_shard_job``), then ``check_store``, and prints in one run:

* per job: wall, CPU (user + system, from ``wait4``), of it system, the write phase's system CPU, peak RSS,
  bytes per node, encode CPU, CPU per phase; the crc32c of every shard object (compare runs and versions);
* bytes per node; the **compression floor**: CPU time to encode the same stored values with the same codec
  chain (transpose + blosc) and nothing else, measured in this run as the jobs ran (a fresh process per
  shard, ``--jobs`` at a time: the same sharing of caches and memory bandwidth) and once in this process
  alone (which alone moves by +-8 % between identical runs); the store stage's
  CPU / floor and the write phase's CPU / floor;
* wall per shard job, peak RSS, and with ``--all`` the measured wall of the whole stage;
* a cold read of one model's tri + hex coordinates (the shard files dropped from the page cache with
  ``posix_fadvise(DONTNEED)``, fresh process), and the same model read by tensorstore (a second Zarr v3
  implementation) compared with zarr-python's;
* without ``--all``: the extrapolation to the default 16,807 models in shards of ``store.shard_models``.

The encoding choices themselves (layouts, codecs, node orders) are measured by
``benchmarks/bench_store_explore.py``.
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
from spinecohort.virtual.shard_job import run_shard_job
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
import numpy as np
import zarr
t1 = time.perf_counter()
z = zarr.open(sys.argv[1], mode="r")
i = int(sys.argv[2])
tri = z["tri/points"][i]
hexp = np.concatenate([z["hex/volume_points"][i], tri[z["hex/surface_vertex"][:]]])  # the whole hex model
print(time.perf_counter() - t1, t1 - t0, tri.shape[0], hexp.shape[0])
"""


#: what Snakemake sets for a job with threads: 1 (snakemake.shell)
ONE_THREAD = {
    k: "1"
    for k in ("OMP_NUM_THREADS", "GOTO_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")
}


def run_jobs(cmds: list[list[str]], jobs: int = 1, logdir: Path | None = None) -> list[dict]:
    """Run processes as threads: 1 jobs, at most ``jobs`` at a time (Snakemake -j``jobs``); per process its
    wall time, CPU time (user + system) and peak RSS from wait4, and its stdout."""
    env = {**os.environ, **ONE_THREAD}
    logdir = Path(logdir or tempfile.mkdtemp(prefix="bench-store-logs-"))
    out, running, todo = [None] * len(cmds), {}, list(enumerate(cmds))
    while todo or running:
        while todo and len(running) < jobs:
            k, cmd = todo.pop(0)
            fo, fe = open(logdir / f"{k}.out", "w"), open(logdir / f"{k}.err", "w")
            proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, text=True, env=env)
            running[proc.pid] = (k, time.perf_counter(), fo, fe)
        pid, status, ru = os.wait4(-1, 0)
        if pid not in running:
            continue
        k, t0, fo, fe = running.pop(pid)
        fo.close()
        fe.close()
        code = os.waitstatus_to_exitcode(status)
        if code != 0:
            raise RuntimeError(f"{cmds[k][:3]} failed ({code}): {(logdir / f'{k}.err').read_text()[-2000:]}")
        out[k] = {
            "wall_s": time.perf_counter() - t0,
            "cpu_s": ru.ru_utime + ru.ru_stime,
            "sys_s": ru.ru_stime,  # kernel: page cache (file writes and reads), page faults
            "rss_mb": ru.ru_maxrss / 1024,
            "out": (logdir / f"{k}.out").read_text(),
        }
    return out


def run(cmd: list[str]) -> dict:
    """One process as a threads: 1 job (see :func:`run_jobs`)."""
    return run_jobs([cmd])[0]


def codec_floor(path: Path, shards: list[int]) -> float:
    """CPU s to encode the stored values of ``shards`` with the store's codec chain alone (transpose to the
    stored order + blosc), one inner chunk at a time: each chunk is read from its shard object and decoded
    outside the timing, then encoded again from model-major order inside it."""
    from numcodecs import blosc

    blosc.set_nthreads(1)  # as in the shard job
    meta = json.loads((path / "zarr.json").read_text())["attributes"]
    cm = meta["chunk_models"]
    slots = meta["shard_models"] // cm
    cpu = 0.0
    for s in shards:
        for name, obj in zip(S.POINT_ARRAYS, S._shard_objects(path, s)[:2]):
            arr = json.loads((path / name / "zarr.json").read_text())
            n_nodes = arr["shape"][1]
            clevel = arr["codecs"][0]["configuration"]["codecs"][-1]["configuration"]["clevel"]
            codec = S._blosc_codecs(clevel)[1]
            data = obj.read_bytes()
            index = np.frombuffer(data[-(16 * slots + 4) : -4], dtype="<u8").reshape(slots, 2)
            for off, nbytes in index:
                if off == 2**64 - 1:
                    continue
                stored = np.frombuffer(codec.decode(data[off : off + nbytes]), np.float32).reshape(3, n_nodes, cm)
                models = np.ascontiguousarray(stored.transpose(S.CHUNK_ORDER))  # (cm, nodes, xyz), as written
                t0 = time.process_time()
                codec.encode(np.ascontiguousarray(models.transpose(S.CHUNK_ORDER)))
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results", help="results folder of a default-config run (inputs)")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--out", help="folder for the benchmark's store and shard files (default: a temporary one)")
    ap.add_argument(
        "--shard-models",
        type=int,
        help="models per shard in this benchmark (default: the config's store.shard_models with --all, else 343)",
    )
    ap.add_argument("--shards", type=int, nargs="+", default=[0, 24, 48])
    ap.add_argument("--all", action="store_true", help="every shard of the grid: the whole store stage")
    ap.add_argument("--jobs", type=int, default=1, help="shard jobs at a time (2 = snakemake -j2 on 2 cores)")
    ap.add_argument("--floor-of", nargs=2, metavar=("STORE", "SHARD"), help=argparse.SUPPRESS)  # one floor process
    a = ap.parse_args(argv)
    if a.floor_of:
        print(codec_floor(Path(a.floor_of[0]), [int(a.floor_of[1])]))
        return 0
    cfg = yaml.safe_load(Path(a.config).read_text())
    if a.shard_models is None:  # the whole stage as the config cuts it; a quick sample in small shards
        a.shard_models = cfg["store"]["shard_models"] if a.all else 343
    L = Layout(a.results)
    inputs = {"ssm": L.ssm, "hex_ssm": L.hex_ssm, "template": L.template, "cohort": L.cohort}
    for k, v in inputs.items():
        if not Path(v).is_file():
            raise SystemExit(f"{v} missing: run `snakemake -j2 {L.hex_ssm}` on the default config first ({k})")
    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="bench-store-", dir=a.out) as tmp:
        stage(Path(tmp), cfg, inputs, a)
    return 0


def stage(tmp: Path, cfg: dict, inputs: dict, a) -> None:
    """init -> shard jobs -> check_store in ``tmp``, then the floor, the cold read and the summary lines."""
    grid = cfg["grid"]
    total = S.n_models(grid["n_modes"], grid["levels"])
    shards = list(range(S.n_shards(total, a.shard_models))) if a.all else a.shards
    store = tmp / "cohort.zarr"
    t_stage = time.perf_counter()
    t0, c0 = time.perf_counter(), time.process_time()
    root = S.create_store_for_run(
        store,
        inputs["ssm"],
        inputs["hex_ssm"],
        inputs["template"],
        grid,
        {**cfg["store"], "shard_models": a.shard_models},
    )
    n_tri, n_hex = root["tri/points"].shape[1], root.attrs["n_hex_nodes"]
    init = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    print(
        f"store: {total} models x ({n_tri} tri + {n_hex} hex nodes), shards of {a.shard_models}, "
        f"format {S.STORE_FORMAT}; init {init['wall_s']:.2f} s; {len(shards)} shard jobs, {a.jobs} at a time"
    )
    cmds, outs = [], {}
    for s in shards:
        outs[s] = {k: str(tmp / f"{s:05d}.{k}") for k in ("quality", "params", "tri_vs_hex", "record")}
        arg = dict(
            store=str(store), shard=s, inputs=inputs, outputs=outs[s], settings=cfg["store"], measure=cfg["measure"]
        )
        cmds.append([sys.executable, "-c", _JOB, json.dumps(arg)])
    t_jobs = time.perf_counter()
    jobs = run_jobs(cmds, a.jobs, tmp)
    jobs_wall = time.perf_counter() - t_jobs
    records = [json.loads(Path(outs[s]["record"]).read_text()) for s in shards]
    phases = ("load", "sample", "quality", "measure", "write", "close")
    print(
        f"{'shard':>5s} {'models':>6s} {'wall s':>7s} {'CPU s':>7s} {'sys s':>6s} {'write sys s':>11s} {'RSS MB':>7s} "
        f"{'B/node':>7s} {'enc CPU s':>9s}  "
        f"CPU s per phase ({', '.join(phases)}; quality = check + repair + Table 3)"
    )
    for s, r, rec in zip(shards, jobs, records):
        n = rec["models"][1] - rec["models"][0]
        cpu = " ".join(f"{rec[f'{k}_cpu_s']:5.1f}" for k in phases)
        print(
            f"{s:>5d} {n:>6d} {r['wall_s']:7.1f} {r['cpu_s']:7.1f} {r['sys_s']:6.1f} {rec['write_sys_s']:11.1f} {r['rss_mb']:7.0f} "
            f"{rec['stored_bytes'] / rec['stored_nodes']:7.3f} {rec['encode_cpu_s']:9.2f}  {cpu}"
        )
    for s, rec in zip(shards, records):  # to compare the stored bytes across runs and code versions
        print(f"  shard {s} crc32c: " + ", ".join(f"{k} {v['crc32c']}" for k, v in rec["objects"].items()))
    chk = run([sys.executable, "-c", _CHECK, str(store)])
    stage_wall = time.perf_counter() - t_stage
    bad = int(chk["out"].strip())
    print(
        f"check_store: {chk['wall_s']:.1f} s wall, {chk['cpu_s']:.1f} s CPU (sys {chk['sys_s']:.1f}), {bad} shards "
        "flagged (unwritten ones)"
    )
    # the floor twice: in this process alone, and as the jobs ran, one fresh
    # process per shard, --jobs at a time: the codec's CPU under the same sharing of caches and memory bandwidth
    floor_alone = codec_floor(store, shards)
    runs = run_jobs([[sys.executable, __file__, "--floor-of", str(store), str(s)] for s in shards], a.jobs)
    floor = sum(float(r["out"].split()[-1]) for r in runs)
    models = sum(r["models"][1] - r["models"][0] for r in records)
    stage_cpu = init["cpu_s"] + sum(j["cpu_s"] for j in jobs) + chk["cpu_s"]
    nbytes = sum(r["stored_bytes"] for r in records)
    nodes = sum(r["stored_nodes"] for r in records)
    enc = sum(r["encode_cpu_s"] for r in records)
    write_cpu = sum(r["write_cpu_s"] for r in records)
    write_sys = sum(r["write_sys_s"] for r in records)
    print(f"\n== {models} models in {len(shards)} shards of {a.shard_models}, {a.jobs} job(s) at a time ==")
    print(f"bytes per node: {nbytes / nodes:.3f} B/node (goal <= 5); {nbytes / 1e9:.2f} GB")
    print(
        f"compression floor (the stored values through transpose + blosc alone, this run): {floor:.2f} s CPU "
        f"measured as the jobs ran (a process per shard, {a.jobs} at a time); {floor_alone:.2f} s in one process "
        f"alone (the jobs' own encode CPU: {enc:.2f} s)"
    )
    print(
        f"store-stage CPU (init + jobs + check): {stage_cpu:.1f} s -> CPU / floor = {stage_cpu / floor:.2f} "
        f"(goal <= 1.5; against the floor alone {stage_cpu / floor_alone:.2f}); write phase alone (rounding, range "
        f"check, transpose, encode, crc32c, file writes): {write_cpu:.1f} s CPU = {write_cpu / floor:.2f} x floor"
    )
    print(
        f"write phase kernel (sys) CPU, all jobs: {write_sys:.1f} s (shard objects written through the page "
        f"cache); check_store: {chk['sys_s']:.1f} s sys"
    )
    stage_sys = sum(j["sys_s"] for j in jobs) + chk["sys_s"]
    print(
        f"of the stage CPU, kernel (sys) time {stage_sys:.1f} s (page cache of the written and hashed shards, page "
        f"faults; it varies several-fold with the machine's memory state), user {stage_cpu - stage_sys:.1f} s -> "
        f"user CPU / floor = {(stage_cpu - stage_sys) / floor:.2f}; load average now {os.getloadavg()[0]:.1f}"
    )
    per_phase = {k: sum(r[f"{k}_cpu_s"] for r in records) for k in phases}
    start_up = sum(j["cpu_s"] for j in jobs) - sum(per_phase.values())
    print(
        "CPU by phase, all jobs: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in per_phase.items())
        + f", interpreter start + imports {start_up:.1f} s, check_store {chk['cpu_s']:.1f} s"
    )
    walls = [j["wall_s"] for j in jobs]
    print(
        f"wall per shard job: {min(walls):.1f}-{max(walls):.1f} s (median {np.median(walls):.1f}); peak RSS per job "
        f"{max(j['rss_mb'] for j in jobs):.0f} MB (goal <= 1500); jobs {jobs_wall:.1f} s wall"
    )
    if a.all:
        print(
            f"whole store stage (init -> {len(shards)} shards, {a.jobs} at a time -> check_store), measured: "
            f"{stage_wall:.1f} s = {stage_wall / 60:.2f} min wall (goal <= 5 min), load average now "
            f"{os.getloadavg()[0]:.1f}"
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
    if not a.all:
        # extrapolation to the default run's shard size on 2 cores, from CPU time (on a quiet machine a
        # single-threaded job's wall is its CPU) and from this run's wall time (inflated by any load)
        sm = cfg["store"]["shard_models"]
        n_sh = S.n_shards(total, sm)
        rounds = math.ceil(n_sh / 2)
        start = float(np.median([r["load_s"] for r in records]))
        load = os.getloadavg()[0]
        for basis, spent, check in (("CPU", "cpu_s", chk["cpu_s"]), ("wall", "wall_s", chk["wall_s"])):
            per_model = (sum(j[spent] for j in jobs) - start * len(jobs)) / models
            job_s = start + sm * per_model
            check_s = check * n_sh * sm / models  # hashing scales with the bytes
            est = init["wall_s"] + rounds * job_s + check_s
            print(
                f"extrapolated ({basis} time{f', load average {load:.1f}' if basis == 'wall' else ''}) to {total} "
                f"models in {n_sh} shards of {sm} on 2 cores: {per_model * 1e3:.1f} ms/model -> {job_s:.0f} s per job, "
                f"{rounds} rounds, check ~{check_s:.0f} s: store stage ~{est / 60:.1f} min (goal <= 5 min)"
            )
    print(f"store size for the whole grid: ~{nbytes / nodes * total * (n_tri + n_hex) / 1e9:.1f} GB")


if __name__ == "__main__":
    sys.exit(main())
