"""Benchmark of the virtual-cohort store stage: init -> shard jobs -> check_store, against the codec floor.

    python benchmarks/bench_store.py [--results results] [--out DIR] [--shard-models 343] [--shards 0 24 48]
                                     [--all] [--jobs 2]
    python benchmarks/bench_store.py --results results --all --jobs 2    # the store stage as the config cuts it
    python benchmarks/bench_store.py --explore [--explore-sample spread|corner] [--explore-orders]

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

``--explore`` (instead of the stage): bytes per node and encode speed of the alternative layouts and codecs
(core Zarr v3 codecs only) on a sample of real models (``EXPLORE_SAMPLES``), and how far each coordinate
rounding moves the measured parameters (docs/explanation/performance.md).  ``--explore --explore-orders [--explore-blocks
224 128 512]``: the chosen codec chain with the nodes of both arrays permuted into other orders
(:func:`node_orders`: Morton, Hilbert, reverse Cuthill-McKee, anatomical parts, long axis, the template's
rings and layers transposed), per blosc block size (docs/explanation/performance.md).
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


EXPLORE_SAMPLES = {
    # shard 0 of 343 models (w1 = w2 = -3, the most deformed corner), its first 49 models
    "corner": [np.arange(0, 49)],
    # one 49-model batch (w3 = 0, w4 = -3..3, w5 = -3..3) from the middle of each level of w1 (2,401 models each)
    "spread": [np.arange(s * 2401 + 3 * 343 + 3 * 49, s * 2401 + 3 * 343 + 4 * 49) for s in range(7)],
}
_BIT, _BYTE = 2, 1  # numcodecs Blosc.BITSHUFFLE, Blosc.SHUFFLE
#: (quantum exponent or None (unrounded) or "um" (int32 um), models per chunk, stored order, blosc clevel
#: (0: zstd 3 alone), shuffle, blosc block KiB); stored order: outermost axis first of (m)odel, (n)ode, (c)oordinate
EXPLORE_VARIANTS = [
    (10, 1, (0, 2, 1), 1, _BIT, 1024),
    (10, 7, (2, 0, 1), 1, _BIT, 1024),
    (10, 7, (2, 1, 0), 1, _BIT, 1024),
    (10, 7, (2, 1, 0), 1, _BYTE, 1024),
    (10, 7, (2, 1, 0), 0, 0, 0),
    (10, 7, (1, 2, 0), 2, _BIT, 256),
    (10, 7, (2, 1, 0), 1, _BIT, 224),
    (10, 7, (2, 1, 0), 2, _BIT, 128),
    (10, 7, (2, 1, 0), 2, _BIT, 192),
    (10, 7, (2, 1, 0), 2, _BIT, 224),  # the chosen encoding
    (10, 7, (2, 1, 0), 2, _BIT, 256),
    (10, 7, (2, 1, 0), 2, _BIT, 1024),
    (10, 7, (2, 1, 0), 2, _BIT, 4096),
    (10, 7, (2, 1, 0), 3, _BIT, 224),
    (10, 7, (2, 1, 0), 4, _BIT, 224),
    (10, 49, (2, 1, 0), 1, _BIT, 224),
    (10, 49, (2, 1, 0), 2, _BIT, 224),
    (9, 7, (2, 1, 0), 1, _BIT, 1024),
    (9, 7, (2, 1, 0), 2, _BIT, 224),
    (None, 7, (2, 1, 0), 2, _BIT, 224),
    ("um", 7, (2, 1, 0), 2, _BIT, 224),
]


def _explore_values(x64: np.ndarray, q) -> np.ndarray:
    if q is None:
        return x64.astype(np.float32)
    if q == "um":
        return np.rint(x64 * 1000).astype(np.int32)
    return (np.rint(x64 * 2.0**q) / 2.0**q).astype(np.float32)


def _encode_chunks(codec, vals: np.ndarray, per: int, order) -> tuple[int, float, int]:
    """(compressed bytes, encode CPU s, raw bytes) of ``vals`` (B, N, 3) encoded by ``codec`` in chunks of
    ``per`` models stored in axis ``order`` (as the store writes its inner chunks); only the encode is timed."""
    nbytes, cpu, raw = 0, 0.0, 0
    for i in range(0, len(vals), per):
        c = np.ascontiguousarray(vals[i : i + per].transpose(order))
        t0 = time.process_time()
        nbytes += len(codec.encode(c))
        cpu += time.process_time() - t0
        raw += c.nbytes
    return nbytes, cpu, raw


def explore_batches(results: Layout, sample: str):
    """The models of ``sample`` (EXPLORE_SAMPLES) batch by batch: (tri (B, N, 3), hex (B, n, 3)) float64 mm,
    sampled with the disc-contact distraction exactly as the shard job does."""
    from spinecohort.mesh.contact import resolve_contact
    from spinecohort.mesh.hex_ssm import HexSSM
    from spinecohort.ssm.model import SSM

    ssm, hex_ssm = SSM.load(results.ssm), HexSSM.load(results.hex_ssm)
    df_t = ssm.deformation_fields(S.DEFAULT_N_MODES).reshape(S.DEFAULT_N_MODES, -1)
    df_h = hex_ssm.fields[: S.DEFAULT_N_MODES].reshape(S.DEFAULT_N_MODES, -1)
    for ids in EXPLORE_SAMPLES[sample]:
        w = S.weights_of(ids)
        t = (ssm.mean.ravel() + w @ df_t).reshape(len(w), *ssm.mean.shape)  # float64, as in the shard job
        h = (hex_ssm.mean.ravel() + w @ df_h).reshape(len(w), *hex_ssm.mean.shape)
        if hex_ssm.contact is not None:
            resolve_contact(t, h, hex_ssm.contact)
        yield t, h


def explore(results: Layout, sample: str, measure_cfg: dict) -> None:
    """B/node and encode MB/s of alternative core-codec layouts on ``sample`` (EXPLORE_SAMPLES), and how far
    each rounding moves the measured parameters (the issue's tolerance: 1e-3 deg, 1e-3 mm)."""
    import pandas as pd
    from numcodecs import Blosc, Zstd, blosc

    from spinecohort.cohort.landmarks import Landmarks
    from spinecohort.measure.spinopelvic import UNITS, measure

    blosc.set_nthreads(1)
    landmarks = Landmarks.from_cohort(results.cohort)
    kw = dict(
        vertical=measure_cfg["vertical_axis"], assumed_age=measure_cfg["assumed_age"], c7_proxy=measure_cfg["c7_proxy"]
    )
    acc = {v: np.zeros(3) for v in EXPLORE_VARIANTS}  # tri bytes, hex bytes, encode CPU s
    raw = dict.fromkeys(EXPLORE_VARIANTS, 0)
    n_tri = n_hex = 0
    moved = {}  # quantum -> (max |d angle| deg, max |d length| mm, worst angle, worst length)
    for t, h in explore_batches(results, sample):
        n_tri += t.shape[0] * t.shape[1]
        n_hex += h.shape[0] * h.shape[1]
        p64 = measure(t, landmarks, **kw)
        num = [c for c in p64.columns if pd.api.types.is_float_dtype(p64[c])]
        for q in (10, 9):
            d = (measure(_explore_values(t, q), landmarks, **kw)[num] - p64[num]).abs().max()
            deg = d[[c for c in num if UNITS.get(c) == "deg"]]
            mm = d[[c for c in num if UNITS.get(c) == "mm"]]
            old = moved.get(q, (0.0, 0.0, "", ""))
            moved[q] = (
                max(old[0], deg.max()),
                max(old[1], mm.max()),
                deg.idxmax() if deg.max() > old[0] else old[2],
                mm.idxmax() if mm.max() > old[1] else old[3],
            )
        for v in EXPLORE_VARIANTS:
            q, per, order, clevel, shuffle, block = v
            codec = Zstd(3) if clevel == 0 else Blosc("zstd", clevel, shuffle, block << 10)
            for k, x in enumerate((t, h)):
                nbytes, cpu, nraw = _encode_chunks(codec, _explore_values(x, q), per, order)
                acc[v][k] += nbytes
                acc[v][2] += cpu
                raw[v] += nraw
    n = sum(map(len, EXPLORE_SAMPLES[sample]))
    print(f"\nExplore ({sample}: {n} models, {n_tri // n} tri + {n_hex // n} hex nodes each), core codecs only")
    print(
        f"{'values':<22s} {'models/chunk':>12s} {'order':>6s} {'codec':<36s} {'B/node':>7s} {'tri':>6s} {'hex':>6s} {'enc MB/s':>9s}"
    )
    for v, (bt, bh, cpu) in acc.items():
        q, per, order, clevel, shuffle, block = v
        vals = {None: "float32 mm, unrounded", "um": "int32 um"}.get(q, f"float32 mm / 2^-{q}")
        codec = (
            "zstd 3, no shuffle"
            if clevel == 0
            else f"blosc {['no', 'byte', 'bit'][shuffle]}shuffle clevel {clevel}, {block} KiB"
        )
        axes = "".join("mnc"[k] for k in order)
        print(
            f"{vals:<22s} {per:>12d} {axes:>6s} {codec:<36s} {(bt + bh) / (n_tri + n_hex):7.3f} {bt / n_tri:6.3f} "
            f"{bh / n_hex:6.3f} {raw[v] / max(cpu, 1e-9) / 1e6:9.0f}"
        )
    for q, (deg, mm, wdeg, wmm) in moved.items():
        print(
            f"2^-{q} mm rounding of the tri model moves the parameters by <= {deg:.2e} deg ({wdeg}), {mm:.2e} mm ({wmm})"
        )


def _spread_bits(v: np.ndarray, bits: int, dims: int = 3) -> np.ndarray:
    """Bit k of each v (uint64) moved to bit k * dims (the Morton interleave of one axis)."""
    out = np.zeros_like(v)
    for k in range(bits):
        out |= ((v >> np.uint64(k)) & np.uint64(1)) << np.uint64(k * dims)
    return out


def _grid_cells(xyz: np.ndarray, bits: int) -> np.ndarray:
    """Coordinates (N, 3) as integer cells (N, 3) uint64 of one cubic grid of 2^bits cells along the longest
    extent of the bounding box (isotropic: the same cell size on every axis)."""
    lo, ext = xyz.min(0), np.ptp(xyz, axis=0).max()
    return np.minimum(((xyz - lo) / ext * 2**bits).astype(np.int64), 2**bits - 1).astype(np.uint64)


def morton_order(xyz: np.ndarray, bits: int = 10) -> np.ndarray:
    """Node order (N,) by the 3-D Morton (Z-order) code of ``xyz`` on a 2^bits grid (ties: template order)."""
    c = _grid_cells(xyz, bits)
    code = _spread_bits(c[:, 0], bits) << np.uint64(2) | _spread_bits(c[:, 1], bits) << np.uint64(1)
    return np.argsort(code | _spread_bits(c[:, 2], bits), kind="stable")


def hilbert_order(xyz: np.ndarray, bits: int = 10) -> np.ndarray:
    """Node order (N,) by the 3-D Hilbert index of ``xyz`` on a 2^bits grid (Skilling, "Programming the
    Hilbert curve", AIP Conf. Proc. 707, 2004: axes -> transposed index, vectorized; ties: template order)."""
    x = _grid_cells(xyz, bits).astype(np.int64)
    n = x.shape[1]
    q = 1 << (bits - 1)
    while q > 1:  # inverse undo of the excess work
        p = q - 1
        for i in range(n):
            hi = (x[:, i] & q) != 0
            x[hi, 0] ^= p
            lo = ~hi
            t = (x[lo, 0] ^ x[lo, i]) & p
            x[lo, 0] ^= t
            x[lo, i] ^= t
        q >>= 1
    for i in range(1, n):  # Gray encode
        x[:, i] ^= x[:, i - 1]
    t = np.zeros(len(x), np.int64)
    q = 1 << (bits - 1)
    while q > 1:
        t[(x[:, n - 1] & q) != 0] ^= q - 1
        q >>= 1
    x ^= t[:, None]
    h = np.zeros(len(x), np.int64)
    for b in range(bits - 1, -1, -1):  # the transposed index, axis 0 most significant
        for i in range(n):
            h = (h << 1) | ((x[:, i] >> b) & 1)
    return np.argsort(h, kind="stable")


def rcm_order(n_nodes: int, cells: list[np.ndarray]) -> np.ndarray:
    """Reverse Cuthill-McKee order of the node graph of ``cells`` (each (E, k) node indices; every pair of
    nodes of a cell adjacent), scipy's."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    rows, cols = [], []
    for c in cells:
        for a in range(c.shape[1]):
            for b in range(c.shape[1]):
                if a != b:
                    rows.append(c[:, a])
                    cols.append(c[:, b])
    r, c = np.concatenate(rows), np.concatenate(cols)
    adj = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n_nodes, n_nodes)).tocsr()
    return np.asarray(reverse_cuthill_mckee(adj, symmetric_mode=True), dtype=np.int64)


def part_blocks_order(xyz: np.ndarray, part: np.ndarray, vertical, inner) -> np.ndarray:
    """Node order (N,): the parts one after the other, from the lowest mean height (along ``vertical``) up,
    and inside each part the order ``inner(part_xyz)`` (an argsort of the part's nodes)."""
    up = xyz @ np.asarray(vertical, float)
    labels = np.unique(part)
    height = np.array([up[part == k].mean() for k in labels])
    out = []
    for k in labels[np.argsort(height, kind="stable")]:
        idx = np.flatnonzero(part == k)
        out.append(idx[inner(xyz[idx])])
    return np.concatenate(out)


def hex_node_parts(template: str) -> np.ndarray:
    """Anatomical part of every node of the hex template (n_nodes,) int: its vertebra (body core and shell,
    posterior elements), disc, sacrum, pelvis or femoral head, from the template's element sets; a node
    shared by two parts (a body's endplate and its disc) belongs to the first set that names it."""
    with np.load(template) as z:
        kinds = json.loads(str(z["meta_json"]))["elset_kind"]
        elems = {"hex": z["hexes"], "tri": z["tris"], "lig": z["ligaments"]}
        part = np.full(len(z["nodes"]), -1, np.int64)
        names: dict[str, int] = {}
        for name, kind in kinds.items():
            if kind == "lig":
                continue
            key = name.split("_")
            key = key[1] if key[0] in ("V", "POST") else "_".join(key[:2]) if key[0] == "D" else name
            nodes = np.unique(elems[kind][z[f"elset__{name}"]])
            nodes = nodes[part[nodes] < 0]
            part[nodes] = names.setdefault(key, len(names))
    part[part < 0] = len(names)  # nodes of no element set (none in the default template)
    return part


def transposed_order(part: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Tri node order (N,) with each part's rings swept the other way: a part's vertices are rows of T
    (its most common index step of an edge other than 1, the ring length of the synthetic surfaces), read
    column by column (vertex j of every ring, then j + 1, ...) instead of ring by ring."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    step = np.abs(e[:, 0] - e[:, 1])
    out = []
    for k in np.unique(part):
        idx = np.flatnonzero(part == k)
        steps, count = np.unique(step[(part[e[:, 0]] == k) & (step > 1)], return_counts=True)
        loc = np.arange(len(idx))
        out.append(idx[np.lexsort((loc // steps[np.argmax(count)], loc % steps[np.argmax(count)]))])
    return np.concatenate(out)


def layers_transposed_order(template: str) -> np.ndarray:
    """Hex node order (n,) with the volume nodes (layers of the template's 2-D grid stacked along the
    spine) read grid node by grid node (node j of every layer, then j + 1, ...), the surface nodes as
    they are."""
    with np.load(template) as z:
        layer, n = z["layer_of_node"], len(z["nodes"])
    first = np.searchsorted(layer, layer)  # layers are contiguous blocks of the grid's nodes
    vol = np.lexsort((layer, np.arange(len(layer)) - first))
    return np.concatenate([vol, np.arange(len(layer), n)])


def node_orders(results: Layout, vertical) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Candidate store orders of the nodes, (tri order (N,), hex order (n,)) by name: store position k holds
    template node order[k]."""
    from spinecohort.mesh.hex_ssm import HexSSM
    from spinecohort.ssm.model import SSM

    tri_xyz, hex_xyz = SSM.load(results.ssm).mean, HexSSM.load(results.hex_ssm).mean
    with np.load(results.cohort) as z:
        faces, tri_part = z["faces"], z["part"]
    with np.load(results.template) as z:
        hex_cells = [z["hexes"], z["tris"], z["ligaments"]]
    hex_part = hex_node_parts(results.template)
    up = lambda x: np.argsort(x @ np.asarray(vertical, float), kind="stable")
    same = lambda x: np.arange(len(x))
    orders = {"template (today)": (same(tri_xyz), same(hex_xyz))}
    for name, f in (("Morton 2^10", morton_order), ("Hilbert 2^10", hilbert_order), ("long axis", up)):
        orders[name] = (f(tri_xyz), f(hex_xyz))
    orders["Morton 2^3, tmpl inside"] = (morton_order(tri_xyz, 3), morton_order(hex_xyz, 3))
    orders["RCM"] = (rcm_order(len(tri_xyz), [faces]), rcm_order(len(hex_xyz), hex_cells))
    for name, f in (("Morton", morton_order), ("Hilbert", hilbert_order), ("long axis", up), ("template", same)):
        orders[f"parts + {name}"] = tuple(
            part_blocks_order(x, p, vertical, f) for x, p in ((tri_xyz, tri_part), (hex_xyz, hex_part))
        )
    layers = layers_transposed_order(results.template)
    orders["rings + layers transp."] = (transposed_order(tri_part, faces), layers)
    orders["hex layers transp."] = (same(tri_xyz), layers)
    orders["tri parts + tmpl, hex layers t."] = (orders["parts + template"][0], layers)
    for name, (a, b) in orders.items():
        assert np.array_equal(np.sort(a), np.arange(len(tri_xyz))), name
        assert np.array_equal(np.sort(b), np.arange(len(hex_xyz))), name
    return orders


def explore_orders(results: Layout, sample: str, vertical, blocks_kib=(224, 128, 512), clevel: int = 2) -> None:
    """B/node (tri, hex, both) and encode MB/s of the chosen chain (float32 / 2^-10 mm, 7 models per chunk,
    c n m, blosc zstd ``clevel`` bitshuffle) with the nodes permuted into each of :func:`node_orders`, for
    each blosc block size of ``blocks_kib``.  A permutation moves no value: the rounding error and the
    parameters are those of the template order."""
    from numcodecs import Blosc, blosc

    blosc.set_nthreads(1)
    orders = node_orders(results, vertical)
    keys = [(o, b) for o in orders for b in blocks_kib]
    codecs = {b: Blosc("zstd", clevel, _BIT, b << 10) for b in blocks_kib}
    acc = {k: np.zeros(3) for k in keys}  # tri bytes, hex bytes, encode CPU s
    raw = dict.fromkeys(keys, 0)
    n_tri = n_hex = 0
    per = S.default_chunk_models(S.DEFAULT_SHARD_MODELS)
    with np.load(results.template) as z:  # hex nodes n_vol.. are the tri vertices surface_vertex, by construction
        surface, n_vol = z["surface_vertex"], int(z["n_hex_nodes"])
    copies, vol_bytes = 0, 0  # exact copies of tri coordinates in the hex array; bytes of the volume nodes alone
    for t, h in explore_batches(results, sample):
        n_tri += t.shape[0] * t.shape[1]
        n_hex += h.shape[0] * h.shape[1]
        copies += int(np.count_nonzero((h[:, n_vol:] == t[:, surface]).all(axis=2)))
        vol_bytes += _encode_chunks(codecs[blocks_kib[0]], S.quantize_mm(h[:, :n_vol]), per, S.CHUNK_ORDER)[0]
        for a, x in enumerate((t, h)):
            vals = S.quantize_mm(x)
            for o, perm in orders.items():
                for b in blocks_kib:
                    nbytes, cpu, nraw = _encode_chunks(codecs[b], vals[:, perm[a]], per, S.CHUNK_ORDER)
                    acc[o, b][a] += nbytes
                    acc[o, b][2] += cpu
                    raw[o, b] += nraw
    n = sum(map(len, EXPLORE_SAMPLES[sample]))
    print(
        f"\nNode orders ({sample}: {n} models, {n_tri // n} tri + {n_hex // n} hex nodes each); float32 / 2^-10 mm, "
        f"{per} models per chunk, c n m, blosc zstd clevel {clevel} bitshuffle"
    )
    print(f"{'node order':<32s} {'block KiB':>9s} {'B/node':>7s} {'tri':>6s} {'hex':>6s} {'enc MB/s':>9s}")
    for (o, b), (bt, bh, cpu) in acc.items():
        print(
            f"{o:<32s} {b:>9d} {(bt + bh) / (n_tri + n_hex):7.3f} {bt / n_tri:6.3f} {bh / n_hex:6.3f} "
            f"{raw[o, b] / max(cpu, 1e-9) / 1e6:9.0f}"
        )
    tri_bytes = acc["template (today)", blocks_kib[0]][0]
    print(
        f"hex nodes that are exact copies of their tri vertex: {copies / n:.0f} of {n_hex // n} per model; the tri "
        f"array + the {n_vol} hex volume nodes alone (template order, {blocks_kib[0]} KiB): "
        f"{(tri_bytes + vol_bytes) / (n_tri + n_hex):.3f} B per node of both arrays"
    )


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
    ap.add_argument("--explore", action="store_true")
    ap.add_argument("--explore-sample", choices=sorted(EXPLORE_SAMPLES), default="spread")
    ap.add_argument("--explore-orders", action="store_true", help="with --explore: node orders instead of codecs")
    ap.add_argument("--explore-blocks", type=int, nargs="+", default=[224, 128, 512], help="blosc block KiB")
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
    if a.explore and a.explore_orders:
        explore_orders(L, a.explore_sample, cfg["measure"]["vertical_axis"], a.explore_blocks)
        return 0
    if a.explore:
        explore(L, a.explore_sample, cfg["measure"])
        return 0
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
    with np.load(inputs["ssm"]) as z:
        n_tri = z["mean"].shape[0]
    with np.load(inputs["hex_ssm"]) as z:
        n_hex = z["mean"].shape[0]
    with np.load(inputs["template"]) as z:
        surface_vertex = z["surface_vertex"]
    S.create_store(
        store,
        n_tri,
        n_hex,
        grid["n_modes"],
        grid["levels"],
        a.shard_models,
        {},
        cfg["store"]["encoding"],
        surface_vertex=surface_vertex,
    )
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
