"""How the shard files are written: kernel (sys) CPU of the page cache, measured per write variant.

    python benchmarks/bench_store_io.py [--out DIR] [--rounds 5] [--jobs 7] [--parallel 2]
                                        [--variants buffered fadvise sync_file_range direct]

One "stage" = ``--jobs`` shard jobs (each a forked process, ``--parallel`` at a time, like ``snakemake -j2``),
each writing the two point-array objects of one default 2,401-model shard (343 encoded chunks of 3.0 MB
(tri) and 2.4 MB (hex) plus the index: 1.84 GB, the sizes of the real format-3 shards; the bytes are random,
the page cache does not look at them) chunk by chunk and hashing them with sha256 as ``ShardWriter`` does;
then the check in a fresh process: ``file_sha256`` of every object (buffered reads, ``check_store``
before ``object_sha256``), then ``object_sha256`` (``O_DIRECT`` reads, a reader thread ahead of the hash). Stages of the variants run interleaved, ``--rounds`` times; per stage it
prints user / sys CPU (wait4 of every job) and wall, whether every written object's sha256 equals the bytes
it was given, and the check's CPU and wall. Variants of the write (``WRITERS``):

* ``buffered``: today's ``open(..., "wb").write(chunk)`` (through the page cache; pages stay cached);
* ``fadvise``: buffered, then ``os.fdatasync`` + ``posix_fadvise(DONTNEED)`` when the object is complete;
* ``sync_file_range``: buffered; every 32 MiB ``sync_file_range(WRITE)`` of that window and
  ``sync_file_range(WAIT_BEFORE | WRITE | WAIT_AFTER)`` + ``posix_fadvise(DONTNEED)`` of the one before
  (libc through ctypes), ``fdatasync`` + ``DONTNEED`` at the end;
* ``direct``: ``store.zarr_store.DirectWriter`` (``O_DIRECT`` through an mmap-aligned 8 MiB buffer).
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from spinecohort.store import zarr_store as S

#: a default shard (2,401 models = 343 chunks of 7): stored bytes per chunk of the tri and the hex array
CHUNKS, TRI_CHUNK, HEX_CHUNK = 343, 3_000_000, 2_370_000
_WINDOW = 32 << 20
_libc = ctypes.CDLL(None, use_errno=True)
_SFR_WAIT_BEFORE, _SFR_WRITE, _SFR_WAIT_AFTER = 1, 2, 4


def _sync_file_range(fd: int, off: int, n: int, flags: int) -> None:
    f = _libc.sync_file_range
    f.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
    if f(fd, off, n, flags) != 0:
        raise OSError(ctypes.get_errno(), "sync_file_range")


def write_buffered(path: Path, chunks, drop: str = "") -> str:
    sha = hashlib.sha256()
    with open(path, "wb") as f:
        done = synced = 0
        for data in chunks:
            f.write(data)
            sha.update(data)
            done += len(data)
            if drop == "window" and done - synced >= _WINDOW:
                f.flush()
                fd = f.fileno()
                _sync_file_range(fd, synced, done - synced, _SFR_WRITE)
                if synced:
                    prev = max(0, synced - _WINDOW)
                    _sync_file_range(fd, prev, synced - prev, _SFR_WAIT_BEFORE | _SFR_WRITE | _SFR_WAIT_AFTER)
                    os.posix_fadvise(fd, prev, synced - prev, os.POSIX_FADV_DONTNEED)
                synced = done
        if drop:
            f.flush()
            os.fdatasync(f.fileno())
            os.posix_fadvise(f.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
    return sha.hexdigest()


def write_direct(path: Path, chunks) -> str:
    sha = hashlib.sha256()
    with S.DirectWriter(path) as f:
        for data in chunks:
            f.write(data)
            sha.update(data)
    return sha.hexdigest()


WRITERS = {
    "buffered": write_buffered,
    "fadvise": lambda p, c: write_buffered(p, c, "close"),
    "sync_file_range": lambda p, c: write_buffered(p, c, "window"),
    "direct": write_direct,
}

_CHECK = """
import json, sys
from spinecohort.store.zarr_store import file_sha256, object_sha256
digest = file_sha256 if sys.argv[1] == "buffered" else object_sha256
print(json.dumps({f: digest(f) for f in json.loads(sys.argv[2])}))
"""


def run_job(variant: str, folder: Path, job: int, data: dict) -> None:
    for name, chunks in data.items():
        tmp = folder / f"{name}.{job}.partial"
        digest = WRITERS[variant](tmp, chunks)
        os.replace(tmp, folder / f"{name}.{job}")
        (folder / f"{name}.{job}.sha").write_text(digest)


def stage(variant: str, folder: Path, n_jobs: int, parallel: int, data: dict) -> dict:
    t0 = time.perf_counter()
    running, todo, user, sys_ = set(), list(range(n_jobs)), 0.0, 0.0
    while todo or running:
        while todo and len(running) < parallel:
            j = todo.pop(0)
            pid = os.fork()
            if pid == 0:
                code = 0
                try:
                    run_job(variant, folder, j, data)
                except BaseException as e:  # noqa: BLE001 - report and exit the child
                    print(f"job {j}: {e!r}", file=sys.stderr)
                    code = 1
                os._exit(code)
            running.add(pid)
        pid, status, ru = os.wait4(-1, 0)
        running.discard(pid)
        if os.waitstatus_to_exitcode(status):
            raise RuntimeError(f"a {variant} job failed")
        user += ru.ru_utime
        sys_ += ru.ru_stime
    return {"user": user, "sys": sys_, "wall": time.perf_counter() - t0}


def check(mode: str, files: list[Path]) -> tuple[dict, dict]:
    import json

    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHECK, mode, json.dumps([str(f) for f in files])], stdout=subprocess.PIPE, text=True
    )
    out = proc.stdout.read()
    _, status, ru = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status):
        raise RuntimeError("check failed")
    return {"user": ru.ru_utime, "sys": ru.ru_stime, "wall": time.perf_counter() - t0}, json.loads(out)


def machine_sys() -> float:
    """System-wide kernel CPU s (system + irq + softirq of /proc/stat): includes the writeback threads that
    flush a buffered writer's dirty pages, which no job's rusage shows (and any other process's)."""
    f = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    return (int(f[3]) + int(f[6]) + int(f[7])) / os.sysconf("SC_CLK_TCK")


def meminfo() -> str:
    m = dict(line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines())
    gb = {k: int(m[k].split()[0]) / 2**20 for k in ("MemFree", "Cached", "Dirty")}
    return f"free {gb['MemFree']:4.1f} cached {gb['Cached']:4.1f} dirty {gb['Dirty']:3.1f} GB"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="folder for the written files (default: a temporary one)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--jobs", type=int, default=7, help="shard jobs per stage (7 = the default store)")
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--variants", nargs="+", default=list(WRITERS), choices=list(WRITERS))
    a = ap.parse_args(argv)
    rng = np.random.default_rng(16)
    data, want = {}, {}
    for name, size in (("tri", TRI_CHUNK), ("hex", HEX_CHUNK)):
        sizes = size + rng.integers(-size // 50, size // 50, CHUNKS)
        data[name] = [rng.bytes(int(n)) for n in sizes] + [rng.bytes(16 * CHUNKS + 4)]
        want[name] = hashlib.sha256(b"".join(data[name])).hexdigest()
    per_job = sum(map(len, data["tri"] + data["hex"]))
    print(
        f"{a.jobs} jobs x {per_job / 1e9:.2f} GB ({a.parallel} at a time) per stage, {a.rounds} rounds; "
        f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}"
    )
    print(
        f"{'round':>5s} {'variant':<16s} {'user s':>6s} {'sys s':>6s} {'wall s':>6s} {'mach.sys':>8s} {'same':>4s}  "
        f"{'check: user sys wall':>20s}  {'O_DIRECT check':>20s}  memory before / after the writes, load"
    )
    rows = []
    for r in range(a.rounds):
        for v in a.variants:
            folder = Path(tempfile.mkdtemp(prefix=f"io-{v}-", dir=a.out))
            try:
                before, k0 = meminfo(), machine_sys()
                w = stage(v, folder, a.jobs, a.parallel, data)
                os.sync()  # the buffered variants' dirty pages are flushed (by the kernel's threads) here
                w["machine_sys"] = machine_sys() - k0
                after = meminfo()
                files = [folder / f"{n}.{j}" for j in range(a.jobs) for n in data]
                ck, got = check("buffered", files)
                dk, got_d = check("direct", files)
                same = all(
                    got[str(f)]
                    == got_d[str(f)]
                    == want[f.name.split(".")[0]]
                    == (f.parent / (f.name + ".sha")).read_text()
                    for f in files
                )
            finally:
                shutil.rmtree(folder)
            rows.append((v, w, ck, dk, same))
            print(
                f"{r:>5d} {v:<16s} {w['user']:6.1f} {w['sys']:6.1f} {w['wall']:6.1f} {w['machine_sys']:8.1f} {'yes' if same else 'NO':>4s}  "
                f"{ck['user']:6.1f} {ck['sys']:6.1f} {ck['wall']:6.1f}  {dk['user']:6.1f} {dk['sys']:6.1f} {dk['wall']:6.1f}"
                f"  {before} / {after}, load {os.getloadavg()[0]:.1f}",
                flush=True,
            )
    print("\nmedian (min-max) over the rounds, per stage of", a.jobs, "jobs:")
    for v in a.variants:
        sel = [row for row in rows if row[0] == v]

        def stat(key, part):
            x = [row[part][key] for row in sel]
            return f"{np.median(x):6.1f} ({min(x):.1f}-{max(x):.1f})"

        print(
            f"{v:<16s} write user {stat('user', 1)} sys {stat('sys', 1)} wall {stat('wall', 1)} machine sys {stat('machine_sys', 1)}; check user "
            f"{stat('user', 2)} sys {stat('sys', 2)} wall {stat('wall', 2)}; O_DIRECT check sys {stat('sys', 3)} "
            f"wall {stat('wall', 3)}; bytes identical {all(row[4] for row in sel)}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
