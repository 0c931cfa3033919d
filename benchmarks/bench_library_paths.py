"""The store stage's wall with its hand-written shard writer against zarr-python writing the same shards.

    python benchmarks/bench_library_paths.py --results results --out /tmp/bench-lib [--rounds 3]

Needs the inputs of the shard jobs of a default-config run (ssm, hex SSM, template, cohort under
``--results``; read only).  Each round runs the store stage once per variant, in an order rotated from round
to round (the machine's load drifts; interleaving spreads it over the variants): a fresh store of the
config's grid and ``store.shard_models`` under ``--out``, every shard as its own process with Snakemake's
one-thread environment, two at a time (``snakemake -j2`` on two cores: the ``sample_shard`` jobs,
``virtual.shard_job.run_shard_job``), then the ``check_store`` job; the store is deleted after each run.

* ``hand``: as committed (``store.writer.ShardWriter`` writes the sharding format itself, streaming);
* ``zarr``: the shard objects written by zarr-python's sharding codec (``array[a:b] = values``; the same
  codecs, chunks and shards).  zarr-python cannot stream a shard: each partial write reads the shard object
  and writes it again whole, and a whole-shard write holds the shard's decoded values (8,407 models x 92,335
  nodes x 12 B = 9.3 GB per job).  So the values are handed over in ``--flush-models`` blocks (1,232 by
  default: ~1.4 GB per job) and the crc32c of each object, which zarr does not report, is read back.

The store stage's other I/O uses library paths (buffered files, pandas ``to_csv``, ``numpy.load``); their
measurement against hand-written versions, and the command that reproduces it, are in
docs/explanation/library-paths.md.

Printed: per run, the shard jobs' wall (the stage a user waits for), ``check_store``'s wall, their sum,
each job's CPU, kernel CPU and peak RSS, and whether the stored bytes (every shard object's crc32c) and the
shard tables (sha256) equal the ``hand`` run's; then per variant the median and range of the stage wall, the
paired ratio to ``hand`` in the same round, and the saving ``(library - hand) / library``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_store  # noqa: E402  (the sibling benchmark's job runner)

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
VARIANTS = ("hand", "zarr")
_JOB = """
import json, sys
sys.path.insert(0, {here!r})
import bench_library_paths as B
a = json.loads(sys.argv[1])
B.use(a["variant"], a["flush_models"])
from spinecohort.virtual.shard_job import run_shard_job
run_shard_job(a["store"], a["shard"], a["inputs"], a["outputs"], a["settings"], a["measure"])
"""
_CHECK = """
import sys
sys.path.insert(0, {here!r})
import bench_library_paths as B
B.use(sys.argv[2], 0)
from spinecohort.store.integrity import shard_problems
print(len(shard_problems(sys.argv[1])))
"""


# ------------------------------------------------------------------------------- the library path
def zarr_shard_writer(flush_models: int):
    """A ``ShardWriter`` whose shard objects zarr-python writes: the same rounding and chunk forming, then the
    values in logical order handed to ``zarr.Array.__setitem__`` every ``flush_models`` models."""
    import zarr

    from spinecohort.store.integrity import invalidate_shard, object_crc32c
    from spinecohort.store.writer import ShardWriter

    class ZarrShardWriter(ShardWriter):
        def __init__(self, path, shard: int):
            super().__init__(path, shard)
            self.abort()  # no objects of our own: zarr writes them
            root = zarr.open_group(str(self.path), mode="r+")
            self._arrays = {name: root[name] for name in self.objects}
            rows = -(-flush_models // self.chunk) * self.chunk + self.chunk
            self._pending = {name: np.empty((rows, n, 3), np.float32) for name, n in self.n_nodes.items()}
            self._flushed = 0

        def add(self, tri, hexp) -> None:
            super().add(tri, hexp)
            if self.n_written - self._flushed >= flush_models:
                self._flush()

        def _append(self, name: str, slot: int, chunk: np.ndarray) -> None:
            m0 = slot * self.chunk - self._flushed
            self._pending[name][m0 : m0 + self.chunk] = chunk.transpose(2, 1, 0)  # the library takes logical order

        def _flush(self) -> None:
            t0 = time.process_time()
            n, a = self.n_written - self._flushed, self.start + self._flushed
            for name, arr in self._arrays.items():
                arr[a : a + n] = self._pending[name][:n]
            self._flushed = self.n_written
            self.encode_cpu_s += time.process_time() - t0

        def close(self) -> dict:
            if self.n_written > self._flushed:
                self._flush()
            objects = {}
            for obj in self.objects.values():
                objects[str(obj.relative_to(self.path))] = {"crc32c": object_crc32c(obj), "bytes": obj.stat().st_size}
                self.stored_bytes += obj.stat().st_size
            return self._finish(objects)

        def abort(self) -> None:
            super().abort()
            if hasattr(self, "_arrays"):
                invalidate_shard(self.path, self.shard)

    return ZarrShardWriter


def use(variant: str, flush_models: int) -> None:
    """Swap the hand-written shard writer for zarr-python's in this process (``variant`` "zarr")."""
    import spinecohort.virtual.shard_job as job

    if variant == "zarr" and flush_models:
        job.ShardWriter = zarr_shard_writer(flush_models)


# ------------------------------------------------------------------------------------------- the stage
def run_jobs(cmds: list[list[str]], jobs: int, logdir: Path) -> tuple[float, list[dict]]:
    """Run the processes ``jobs`` at a time (``bench_store.run_jobs``); (wall of all, per process records)."""
    t_all = time.perf_counter()
    out = bench_store.run_jobs(cmds, jobs, logdir)
    return time.perf_counter() - t_all, out


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def stage(variant: str, folder: Path, cfg: dict, inputs: dict, flush_models: int) -> dict:
    """init_store, the shard jobs two at a time, check_store; the walls, the jobs' resources, the digests."""
    from spinecohort.store import zarr_store as S

    grid, shard_models = cfg["grid"], cfg["store"]["shard_models"]
    folder.mkdir(parents=True)
    store = folder / "cohort.zarr"
    S.create_store_for_run(store, inputs["ssm"], inputs["hex_ssm"], inputs["template"], grid, cfg["store"])
    shards = range(S.n_shards(S.n_models(grid["n_modes"], grid["levels"]), shard_models))
    cmds, outs = [], {}
    for s in shards:
        outs[s] = {k: str(folder / f"{s:05d}.{k}") for k in ("quality", "params", "tri_vs_hex", "record")}
        arg = dict(
            variant=variant, flush_models=flush_models, store=str(store), shard=s, inputs=inputs,
            outputs=outs[s], settings=cfg["store"], measure=cfg["measure"],
        )  # fmt: skip
        cmds.append([sys.executable, "-c", _JOB.format(here=str(HERE)), json.dumps(arg)])
    jobs_wall, jobs = run_jobs(cmds, 2, folder)
    check_wall, (chk,) = run_jobs(
        [[sys.executable, "-c", _CHECK.format(here=str(HERE)), str(store), variant]], 1, folder
    )
    if int(chk["out"].strip()) != 0:
        raise RuntimeError(f"{variant}: check_store flags {chk['out'].strip()} shards")
    records = [json.loads(Path(outs[s]["record"]).read_text()) for s in shards]
    return {
        "variant": variant,
        "jobs_wall_s": jobs_wall,
        "check_wall_s": check_wall,
        "stage_wall_s": jobs_wall + check_wall,
        "jobs": [{k: v for k, v in j.items() if k != "out"} for j in jobs],
        "check": {k: v for k, v in chk.items() if k != "out"},
        "crc32c": {k: v["crc32c"] for r in records for k, v in r["objects"].items()},
        "tables": {f"{s:05d}.{k}": sha256(outs[s][k]) for s in shards for k in ("quality", "params", "tri_vs_hex")},
        "load_s": [r["load_s"] for r in records],
        "close_s": [r["close_s"] for r in records],
        "write_s": [r["write_s"] for r in records],
    }


def summary(runs: list[dict], variants: list[str]) -> None:
    """Per variant: median and range of each wall, the paired ratio to ``hand`` of the same round, the saving."""
    hand = {r["round"]: r for r in runs if r["variant"] == "hand"}
    print(f"\n{'variant':9s} {'key':12s} {'median s':>9s} {'range s':>15s} {'/ hand (paired)':>22s} {'saving':>7s}")
    for v in variants:
        mine = [r for r in runs if r["variant"] == v]
        for key in ("jobs_wall_s", "check_wall_s", "stage_wall_s"):
            x = [r[key] for r in mine]
            ratios = [r[key] / hand[r["round"]][key] for r in mine if r["round"] in hand]
            rtxt = f"{statistics.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})" if ratios else "-"
            h = [hand[r["round"]][key] for r in mine if r["round"] in hand]
            save = (statistics.median(x) - statistics.median(h)) / statistics.median(x) if h else float("nan")
            print(f"{v:9s} {key:12s} {statistics.median(x):9.1f} {min(x):7.1f}-{max(x):7.1f} {rtxt:>22s} {save:7.1%}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results", help="results folder of a default-config run (inputs, read only)")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--out", required=True, help="scratch folder (a store of ~8 GB at a time, deleted after each run)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--flush-models", type=int, default=1232, help="zarr variant: models per zarr write")
    ap.add_argument("--json", help="also write every run's numbers to this file")
    a = ap.parse_args(argv)
    from spinecohort.layout import Layout

    cfg = yaml.safe_load(Path(a.config).read_text())
    L = Layout(a.results)
    inputs = {"ssm": L.ssm, "hex_ssm": L.hex_ssm, "template": L.template, "cohort": L.cohort}
    for k, v in inputs.items():
        if not Path(v).is_file():
            raise SystemExit(f"{v} missing: run the default config up to the hex SSM first ({k})")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs, reference = [], None
    for rnd in range(a.rounds):
        order = a.variants[rnd % len(a.variants) :] + a.variants[: rnd % len(a.variants)]
        for v in order:
            folder = out / f"{v}-{rnd}"
            shutil.rmtree(folder, ignore_errors=True)
            try:
                r = stage(v, folder, cfg, inputs, a.flush_models)
            finally:
                shutil.rmtree(folder, ignore_errors=True)
            r["round"] = rnd
            if v == "hand" and reference is None:
                reference = r
            same_bytes = reference is None or r["crc32c"] == reference["crc32c"]
            same_tables = reference is None or r["tables"] == reference["tables"]
            r["same_bytes"], r["same_tables"] = same_bytes, same_tables
            jobs = ", ".join(
                f"{j['wall_s']:.1f} s ({j['cpu_s']:.1f} CPU, {j['sys_s']:.1f} sys, {j['rss_mb']:.0f} MB)"
                for j in r["jobs"]
            )
            print(
                f"round {rnd} {v:9s} shard jobs {r['jobs_wall_s']:6.1f} s + check_store {r['check_wall_s']:5.1f} s "
                f"= {r['stage_wall_s']:6.1f} s; jobs: {jobs}; check {r['check']['cpu_s']:.1f} CPU "
                f"({r['check']['sys_s']:.1f} sys); same stored bytes: {same_bytes}, same tables: {same_tables}",
                flush=True,
            )
            runs.append(r)
            if a.json:
                Path(a.json).write_text(json.dumps(runs, indent=1))
    summary(runs, a.variants)
    return 0


if __name__ == "__main__":
    sys.exit(main())
