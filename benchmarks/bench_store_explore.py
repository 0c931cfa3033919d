"""The store's encoding choices, measured: bytes per node and encode speed of alternative layouts, codecs and
node orders (core Zarr v3 codecs only) on a sample of real models, and how far each coordinate rounding moves
the measured parameters.

    python benchmarks/bench_store_explore.py --results results [--sample spread|corner]
    python benchmarks/bench_store_explore.py --results results --orders [--blocks 224 128 512]

Needs the inputs of the shard jobs of a default-config run (ssm, hex SSM, template, cohort under
``--results``).  ``--orders``: the chosen codec chain with the nodes of both arrays permuted into other orders
(:func:`node_orders`: Morton, Hilbert, reverse Cuthill-McKee, anatomical parts, long axis, the template's
rings and layers transposed), per blosc block size (docs/explanation/performance.md).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml

from spinecohort.layout import Layout
from spinecohort.store import zarr_store as S

ROOT = Path(__file__).resolve().parents[1]


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
    orders = {"template": (same(tri_xyz), same(hex_xyz))}
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
    tri_bytes = acc["template", blocks_kib[0]][0]
    print(
        f"hex nodes that are exact copies of their tri vertex: {copies / n:.0f} of {n_hex // n} per model; the tri "
        f"array + the {n_vol} hex volume nodes alone (template order, {blocks_kib[0]} KiB): "
        f"{(tri_bytes + vol_bytes) / (n_tri + n_hex):.3f} B per node of both arrays"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results", help="results folder of a default-config run (inputs)")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--sample", choices=sorted(EXPLORE_SAMPLES), default="spread")
    ap.add_argument("--orders", action="store_true", help="node orders instead of codecs")
    ap.add_argument("--blocks", type=int, nargs="+", default=[224, 128, 512], help="blosc block KiB (--orders)")
    a = ap.parse_args(argv)
    cfg = yaml.safe_load(Path(a.config).read_text())
    L = Layout(a.results)
    if a.orders:
        explore_orders(L, a.sample, cfg["measure"]["vertical_axis"], a.blocks)
    else:
        explore(L, a.sample, cfg["measure"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
