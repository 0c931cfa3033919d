"""The sharded Zarr v3 store of the virtual cohort (``results/cohort.zarr``), core Zarr v3 codecs only.

Layout (one store, written shard by shard by independent jobs)::

    weights            (n_models, n_modes)           float64, SD units; one chunk per shard (zstd)
    tri/points         (n_models, n_tri_nodes, 3)    float32 mm; chunk_models models per inner chunk,
                                                     shard_models per shard
    hex/volume_points  (n_models, n_volume_nodes, 3) float32 mm: the hex model's own nodes (vertebral bodies,
                                                     endplates, discs); same chunking
    hex/surface_vertex (n_surface_nodes,)            int32: the tri vertex each remaining hex-model node is
                                                     (posterior elements, sacrum, pelvis, femoral heads: S3 skins
                                                     on the triangulated surface; the same for every model)
    checksums/shard_NNNNN                            per-shard group whose attributes hold the crc32c and size of
                                                     the shard's stored objects; written last, atomically: the
                                                     completion mark

The hex model's nodes (node k = node k+1 of "Mean_Model (Template).inp") are the volume nodes followed by
those tri vertices (:func:`hex_model_points`)::

    hex = np.concatenate([z["hex/volume_points"][i], z["tri/points"][i][z["hex/surface_vertex"][:]]])

Storing the 52,772 surface nodes once instead of twice (format 3 kept them in ``hex/points`` too, as bitwise
copies of the tri vertices) takes the default store from 5.32 to ~3.4 bytes per model node (docs/store.md).

Model IDs are mixed-radix numbers of the SD-level indices, mode 1 most significant
(``model_id = sum_i (w_i + 3) * 7^(5 - i)`` on the default 5 x {-3..3} grid); a shard is the contiguous
ID range ``[shard * shard_models, (shard + 1) * shard_models)``.

Encoding (chosen by measurement, docs/store.md): every array uses only codecs of the Zarr v3 core
specification, so any conforming reader (zarr-python, tensorstore, zarrs, zarr.js, Zarr.jl) decodes
``z["tri/points"][i]`` and ``z["hex/volume_points"][i]`` to float32 millimetres.  Coordinates are rounded to multiples of 2^-10 mm (exact in
float32 for |x| < 16 m, so the stored value *is* the rounded one: error <= 2^-11 mm = 0.49 um), an inner
chunk holds the ``chunk_models`` models along the last mode, and the ``transpose`` codec stores it
coordinate-major with the model axis innermost (x of node 0 of the 7 models, x of node 1, ...), where
neighbouring values share their high bits; ``blosc`` (bitshuffle, zstd level 3, blocks of 8,192 nodes x 7
models) then packs the bit planes.
Sharding codec: one shard object per array per shard, index at the end with crc32c.

:class:`ShardWriter` writes a shard object itself (the sharding format: the encoded inner chunks, then the
index of (offset, nbytes) uint64 pairs and its crc32c), streaming batch by batch with ``O_DIRECT``
(:class:`DirectWriter`, around the page cache), so a job never holds a whole shard; its bytes are identical
to zarr-python's own write of the same array (tested), and a second implementation (tensorstore) reads them
(tested).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import mmap
import os
import signal
import time
from pathlib import Path

import google_crc32c
import numba
import numpy as np
import zarr
from numcodecs import Blosc
from zarr.codecs import BloscCodec, TransposeCodec, ZstdCodec

#: SD levels of the default grid and number of modes (5 x {-3..3} -> 16,807 models).
DEFAULT_LEVELS = (-3, -2, -1, 0, 1, 2, 3)
DEFAULT_N_MODES = 5
DEFAULT_SHARD_MODELS = 2401
#: coordinates are stored as multiples of 2^-QUANTUM_EXP mm (2^-10 mm = 0.98 um; rounding error <= 0.49 um)
QUANTUM_EXP = 10
ENCODINGS = ("float32-q10", "float32")
#: the per-shard coordinate arrays
POINT_ARRAYS = ("tri/points", "hex/volume_points")
SURFACE_VERTEX = "hex/surface_vertex"
#: version 4: the hex model's surface nodes are not stored again (hex/volume_points + hex/surface_vertex);
#: version 3: hex/points held every hex-model node, blosc clevel 2 on 224 KiB blocks (version 2: clevel 1 on
#: 1 MiB blocks; version 1: numcodecs filters); a store of another version is refused, see _open_meta
STORE_FORMAT = "spinecohort.cohort-store/4"
_FORMAT_PREFIX = "spinecohort.cohort-store/"
#: blosc inside each inner chunk: bitshuffle, clevel 2 (blosc's zstd level 3) on blocks of 224 KiB = 8,192
#: nodes x 7 models x 4 B (docs/store.md: -3.6 % of the bytes of clevel 1 on 1 MiB blocks at ~1.8x its encode
#: CPU; 1 MiB and 4 MiB blocks compress worse, blosc's clevel 3 is no better)
BLOSC_CLEVEL = 2
BLOSC_BLOCK_BYTES = 224 << 10
#: transpose of an inner chunk (models, nodes, xyz) -> stored (xyz, nodes, models)
CHUNK_ORDER = (2, 1, 0)
_CHECKSUM_DIR = "checksums"
_EMPTY = 2**64 - 1  # the sharding index's marker of a chunk that is not stored
#: fault injection for the kill-and-resume test: a process with this variable set to a shard number is
#: SIGKILLed by ``ShardWriter.close`` after that shard's first array object is in place (a node failure)
FAULT_KILL_ENV = "SPINECOHORT_FAULT_KILL_SHARD"
# float32 spacing relative to magnitude: one rounding contributes at most half an ulp
_F32_HALF_ULP_REL = 2.0**-24


class StoreVersionError(ValueError):
    """The store was written by another version of spinecohort (its ``format`` attribute differs)."""


# --------------------------------------------------------------------------------------------- IDs
def _levels_array(levels) -> np.ndarray:
    lv = np.asarray(levels, dtype=np.float64)
    if lv.ndim != 1 or lv.size < 1:
        raise ValueError(f"levels must be a non-empty 1-D sequence of SD values, got {levels!r}")
    if np.any(np.diff(lv) <= 0):
        raise ValueError(f"levels must be strictly increasing, got {list(lv)}")
    return lv


def n_models(n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> int:
    """Number of models on the grid: len(levels) ** n_modes (7^5 = 16,807 by default)."""
    if n_modes < 1:
        raise ValueError(f"n_modes must be >= 1, got {n_modes}")
    return len(_levels_array(levels)) ** int(n_modes)


def model_id(weights, levels=DEFAULT_LEVELS) -> np.ndarray:
    """Model IDs of grid weights (..., n_modes) in SD units; mode 1 is the most significant digit.

    On the default grid this is ``sum_i (w_i + 3) * 7^(n_modes - i)``.  Weights must lie on the grid.
    """
    lv = _levels_array(levels)
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim < 1:
        raise ValueError("weights must have a trailing mode axis")
    digit = np.searchsorted(lv, w)
    digit_c = np.clip(digit, 0, lv.size - 1)
    if np.any(np.abs(lv[digit_c] - w) > 1e-9) or np.any(digit >= lv.size):
        raise ValueError(f"weights off the grid levels {list(lv)}")
    place = lv.size ** np.arange(w.shape[-1] - 1, -1, -1, dtype=np.int64)
    return digit_c.astype(np.int64) @ place


def weights_of(ids, n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> np.ndarray:
    """Grid weights (..., n_modes) in SD units of model IDs (...); inverse of :func:`model_id`."""
    lv = _levels_array(levels)
    i = np.asarray(ids)
    if not np.issubdtype(i.dtype, np.integer):
        raise ValueError(f"model IDs must be integers, got dtype {i.dtype}")
    total = lv.size ** int(n_modes)
    if np.any(i < 0) or np.any(i >= total):
        raise ValueError(f"model IDs must lie in [0, {total}), got range [{i.min()}, {i.max()}]")
    place = lv.size ** np.arange(n_modes - 1, -1, -1, dtype=np.int64)
    digits = (i.astype(np.int64)[..., None] // place) % lv.size
    return lv[digits]


def grid_weights(n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> np.ndarray:
    """All grid weights (n_models, n_modes) in SD units, row k = weights of model k."""
    return weights_of(np.arange(n_models(n_modes, levels)), n_modes, levels)


def model_name(ids) -> list[str] | str:
    """``model_00000``-style names of one ID or an array of IDs."""
    if np.ndim(ids) == 0:
        return f"model_{int(ids):05d}"
    return [f"model_{int(k):05d}" for k in np.ravel(ids)]


def n_shards(total_models: int, shard_models: int = DEFAULT_SHARD_MODELS) -> int:
    """Number of shards covering total_models IDs (the last one may be partial)."""
    if shard_models < 1:
        raise ValueError(f"shard_models must be >= 1, got {shard_models}")
    return -(-int(total_models) // int(shard_models))


def shard_range(
    shard: int, shard_models: int = DEFAULT_SHARD_MODELS, total_models: int | None = None
) -> tuple[int, int]:
    """Half-open model-ID range [start, stop) of ``shard``; clipped to total_models when given."""
    if shard_models < 1:
        raise ValueError(f"shard_models must be >= 1, got {shard_models}")
    if shard < 0 or (total_models is not None and shard >= n_shards(total_models, shard_models)):
        raise ValueError(f"shard {shard} out of range for {total_models} models in shards of {shard_models}")
    start = int(shard) * int(shard_models)
    stop = start + int(shard_models)
    return start, stop if total_models is None else min(stop, int(total_models))


# ---------------------------------------------------------------------------------------- encoding
def quantize_mm(x: np.ndarray, encoding: str = "float32-q10") -> np.ndarray:
    """Coordinates (mm, any float dtype) as stored: float32 multiples of 2^-10 mm ("float32-q10") or the
    nearest float32 ("float32").  Rounding happens in float64, so it is exact: |x| * 2^10 < 2^24."""
    if encoding == "float32":
        return np.asarray(x, dtype=np.float32)
    if encoding != "float32-q10":
        raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")
    scale = float(2**QUANTUM_EXP)
    return (np.rint(np.asarray(x, dtype=np.float64) * scale) / scale).astype(np.float32)


@numba.njit(cache=True, inline="always")
def _stored_value_nb(x, quantize):
    """The stored float32 value of one coordinate x mm: :func:`quantize_mm`'s rounding to 2^-10 mm in float64
    (then exact in float32), or the nearest float32."""
    if quantize:
        return np.float32(np.rint(x * 2.0**QUANTUM_EXP)) * np.float32(2.0**-QUANTUM_EXP)
    return np.float32(x)


@numba.njit(cache=True)
def _stored_chunks_nb(x, quantize, chunk, out):
    """The stored values of a batch x (B, N, 3) mm, chunk by chunk in stored order: out (K, 3, N, chunk)
    float32 with out[k, c, n, m] = value of model k * chunk + m, node n, coordinate c (``CHUNK_ORDER``);
    models past B are 0 (the boundary chunk's fill value).  quantize: rint(x * 2^10) / 2^10 in float64,
    cast to float32 (exact, see :func:`quantize_mm`), else the nearest float32.  Returns (min, max, all
    finite) of the stored values.

    One pass for what numpy does in five (scale, rint, cast, rescale, transpose copy) plus the range check:
    the batch is ~1 GB of float64 per shard job's 49 models, so every pass over it costs.
    """
    B, N = x.shape[0], x.shape[1]
    lo, hi, finite = np.inf, -np.inf, True
    for k in range(out.shape[0]):
        for m in range(chunk):
            b = k * chunk + m
            if b >= B:
                for c in range(3):
                    for n in range(N):
                        out[k, c, n, m] = 0.0
                continue
            for n in range(N):
                for c in range(3):
                    v = _stored_value_nb(x[b, n, c], quantize)
                    out[k, c, n, m] = v
                    if not np.isfinite(v):
                        finite = False
                    else:
                        lo = min(lo, v)
                        hi = max(hi, v)
    return lo, hi, finite


#: nodes per block of the linear-formula kernel: its float64 accumulator and float32 rows stay in L1
_LINEAR_BLOCK = 512


@numba.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _fold_first3_nb(fields, c, n0, nb, w, acc):
    """acc[:nb] = w[0] g0 + w[1] g1 + w[2] g2 (g_j = fields[j, c, n0:n0 + nb]): a product, then two
    multiply-adds, the node loop the vector loop."""
    ga, gb, gc = fields[0, c, n0 : n0 + nb], fields[1, c, n0 : n0 + nb], fields[2, c, n0 : n0 + nb]
    wa, wb, wc = w[0], w[1], w[2]
    for i in range(nb):
        a = wa * ga[i]
        a += wb * gb[i]
        a += wc * gc[i]
        acc[i] = a


@numba.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _fold_nb(fields, c, n0, nb, w, j0, j1, src, acc):
    """acc[:nb] = src[:nb] + w[j] g_j for j = j0 .. j1 - 1 in that order, one multiply-add per term, at most
    three terms per pass over acc (they stay in registers between passes).  src may be acc."""
    for j in range(j0, j1, 3):
        k = min(3, j1 - j)
        ga, wa = fields[j, c, n0 : n0 + nb], w[j]
        if k == 3:
            gb, gc, wb, wc = fields[j + 1, c, n0 : n0 + nb], fields[j + 2, c, n0 : n0 + nb], w[j + 1], w[j + 2]
            for i in range(nb):
                a = src[i]
                a += wa * ga[i]
                a += wb * gb[i]
                a += wc * gc[i]
                acc[i] = a
        elif k == 2:
            gb, wb = fields[j + 1, c, n0 : n0 + nb], w[j + 1]
            for i in range(nb):
                a = src[i]
                a += wa * ga[i]
                a += wb * gb[i]
                acc[i] = a
        else:
            for i in range(nb):
                a = src[i]
                a += wa * ga[i]
                acc[i] = a
        src = acc


@numba.njit(cache=True, error_model="numpy")
def _stored_row_nb(acc, nb, quantize, lim, row):
    """row[:nb] = the stored float32 values of acc[:nb] mm (see :func:`quantize_mm`); returns how many are
    not finite or beyond +-lim mm (an integer count: it vectorizes, a min/max reduction would not)."""
    bad = 0
    for i in range(nb):
        v = _stored_value_nb(acc[i], quantize)
        row[i] = v
        bad += not (abs(v) <= lim)
    return bad


@numba.njit(cache=True, error_model="numpy")
def _interleave_nb(rows, nb, q):
    """q[i * C + m] = rows[m, i] for i < nb: the chunk's C models of nb nodes into stored order (model axis
    innermost); the 7-model chunk of the default grid unrolled (2.3 vs 6.9 ms per 56 models)."""
    C = rows.shape[0]
    if C == 7:
        r0, r1, r2, r3, r4, r5, r6 = rows[0], rows[1], rows[2], rows[3], rows[4], rows[5], rows[6]
        for i in range(nb):
            q[i * 7] = r0[i]
            q[i * 7 + 1] = r1[i]
            q[i * 7 + 2] = r2[i]
            q[i * 7 + 3] = r3[i]
            q[i * 7 + 4] = r4[i]
            q[i * 7 + 5] = r5[i]
            q[i * 7 + 6] = r6[i]
    else:
        for i in range(nb):
            for m in range(C):
                q[i * C + m] = rows[m, i]


@numba.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _linear_chunks_nb(fields, weights, shared, level, offsets, moved, quantize, lim, out, rows, acc, base):
    """K inner chunks in stored order, straight from the linear formula: out (K, 3, N, C) float32 with
    out[k, c, n, m] = stored value of sum_j weights[b, j] * fields[j, c, n] + offsets[b, level[n], c] for
    model b = k C + m (the offset only where moved[b] and level[n] >= 0).  fields (J, 3, N) float64 mm,
    weights (K C, J), shared (K,), level (N,), offsets (K C, L, 3) mm; rows (C, NB) float32, acc and base (NB,)
    float64 are scratch.  Returns how many stored values are not finite or beyond +-lim mm.

    The sum is a product then one multiply-add per term, in term order.  ``shared[k]`` (>= 3, or 0: none):
    the first shared[k] weights are the same for chunk k's C models (the default grid's chunk runs along the
    last mode), so that part of their sums is formed once per node block; the remaining terms continue it
    model by model, the same operations in the same order as without sharing (the same bits).  The node
    block is the outer loop, so the fields (11.7 MB for the default tri models) are read from memory once per
    batch, not once per chunk."""
    K, _, N, C = out.shape
    J = fields.shape[0]
    NB = acc.shape[0]
    bad = 0
    for c in range(3):
        for n0 in range(0, N, NB):
            nb = min(NB, N - n0)
            for k in range(K):
                s = shared[k]
                if s:
                    _fold_first3_nb(fields, c, n0, nb, weights[k * C], base)
                    _fold_nb(fields, c, n0, nb, weights[k * C], 3, s, base, base)
                for m in range(C):
                    b = k * C + m
                    src, j0 = base, s
                    if not s:  # the model's own first three terms
                        _fold_first3_nb(fields, c, n0, nb, weights[b], acc)
                        src, j0 = acc, 3
                    _fold_nb(fields, c, n0, nb, weights[b], j0, J, src, acc)
                    if moved[b]:  # the disc-contact distraction: one translation per level, after the formula
                        for i in range(nb):
                            lv = level[n0 + i]
                            if lv >= 0:
                                acc[i] += offsets[b, lv, c]
                    bad += _stored_row_nb(acc, nb, quantize, lim, rows[m])
                q = out[k, c].reshape(N * C)
                _interleave_nb(rows, nb, q[n0 * C : (n0 + nb) * C])
    return bad


def _shared_terms(weights: np.ndarray) -> int:
    """How many leading terms all rows of weights (C, J) weigh alike, as ``_linear_chunks_nb`` takes it: at
    least 3 (its first pass forms three terms), at most J - 1 (each model adds one of its own), else 0."""
    same = np.all(weights == weights[:1], axis=0)
    k = len(same) if same.all() else int(np.argmin(same))
    k = min(k, weights.shape[1] - 1)
    return k if k >= 3 else 0


def linear_fields(mean: np.ndarray, fields: np.ndarray) -> np.ndarray:
    """The terms of ``mean + sum_i w_i fields[i]`` as :class:`LinearPoints` takes them: (J, 3, N) float64 mm,
    coordinate-major, the m fields then the mean, after zero fields that make J a multiple of 3.  mean (N, 3),
    fields (m, N, 3) mm."""
    mean, fields = np.asarray(mean, dtype=np.float64), np.asarray(fields, dtype=np.float64)
    m = len(fields)
    pad = -(m + 1) % 3
    out = np.zeros((pad + m + 1, 3, mean.shape[0]))
    out[pad : pad + m] = fields.transpose(0, 2, 1)
    out[-1] = mean.T
    return out


class LinearPoints:
    """A batch of one point array given by its linear formula, for :meth:`ShardWriter.add`, which forms each
    inner chunk straight in stored order (one numba pass over the batch, :func:`_linear_chunks_nb`): the float64
    coordinates of the batch are never formed.  For the default run's triangulated models that is ~14 ms per
    56 models (the chunk's shared leading terms once, the fields read once per batch) instead of 43 ms for the
    BLAS product, its 109 MB float64 batch and the rounding pass.

    Model b is ``mean + sum_i weights[b, i] * fields[i]`` (``terms`` from :func:`linear_fields`, weights (B, m)
    in the fields' units) plus, where ``offsets`` is given, ``offsets[b, level[n]]`` on node n (level -1:
    none): the disc-contact distraction's level translations (``mesh.contact``), added after the formula as
    ``contact.resolve_contact`` adds them.
    """

    def __init__(self, terms: np.ndarray, weights: np.ndarray, level: np.ndarray | None = None, offsets=None):
        self.terms = np.ascontiguousarray(terms, dtype=np.float64)
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim != 2:
            raise ValueError(f"weights must be (models, modes), got shape {w.shape}")
        m, J = w.shape[1], len(self.terms)
        if self.terms.ndim != 3 or self.terms.shape[1] != 3 or J % 3 or m + 1 > J:
            raise ValueError(f"terms must be linear_fields' (J, 3, N) for {m} weights, got {self.terms.shape}")
        self.weights = np.zeros((len(w), J))
        self.weights[:, J - 1 - m : J - 1] = w
        self.weights[:, J - 1] = 1.0  # the mean
        n = self.terms.shape[2]
        if offsets is None:
            self.level = np.full(n, -1, dtype=np.int64)
            self.offsets = np.zeros((len(w), 1, 3))
        else:
            self.level = np.ascontiguousarray(level, dtype=np.int64)
            self.offsets = np.ascontiguousarray(offsets, dtype=np.float64)
            if (
                self.level.shape != (n,)
                or self.offsets.shape[0] != len(w)
                or self.level.max(initial=-1) >= self.offsets.shape[1]
            ):
                raise ValueError("level must give each of the nodes a row of offsets (models, levels, 3)")
        self.moved = np.abs(self.offsets).max(axis=(1, 2)) > 0

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.weights), self.terms.shape[2], 3)

    def __len__(self) -> int:
        return len(self.weights)

    def stored_chunks(self, quantize: bool, max_abs_mm: float, out: np.ndarray, scratch) -> int:
        """The batch's models into ``out`` (K, 3, N, C) float32, inner chunk by inner chunk in stored order
        (models past the batch: 0, the boundary chunk's fill value); returns the count of values not finite or
        beyond max_abs_mm.  scratch: (rows (C, NB) float32, acc and base (NB,) float64)."""
        K, C = out.shape[0], out.shape[3]
        w, off, moved = self.weights, self.offsets, self.moved
        pad = K * C - len(w)
        if pad < 0:
            raise ValueError(f"{len(w)} models do not fit {K} chunks of {C}")
        if pad:  # zero weights, the mean's included: the model is 0.0 everywhere
            w = np.vstack([w, np.zeros((pad, w.shape[1]))])
            off = np.concatenate([off, np.zeros((pad, *off.shape[1:]))])
            moved = np.concatenate([moved, np.zeros(pad, bool)])
        shared = np.array([_shared_terms(w[k * C : (k + 1) * C]) for k in range(K)], dtype=np.int64)
        return _linear_chunks_nb(
            self.terms, w, shared, self.level, off, moved, quantize, float(max_abs_mm), out, *scratch
        )


def _blosc_codecs(clevel: int) -> tuple[BloscCodec, Blosc]:
    """The core-spec blosc codec of the point arrays and the identical numcodecs compressor the writer uses."""
    cfg = dict(cname="zstd", clevel=int(clevel), blocksize=BLOSC_BLOCK_BYTES)
    return (
        BloscCodec(shuffle="bitshuffle", typesize=4, **cfg),
        Blosc(shuffle=Blosc.BITSHUFFLE, typesize=4, **cfg),
    )


def error_bound_mm(encoding: str, max_abs_mm: float = 512.0) -> float:
    """Largest |decoded - input| in mm for coordinates with |x| <= max_abs_mm.

    "float32-q10": half the 2^-10 mm quantum (the rounded value is exact in float32); "float32": one float32
    rounding, at most 2^-24 |x|.
    """
    if encoding == "float32":
        return _F32_HALF_ULP_REL * max_abs_mm
    if encoding == "float32-q10":
        return 0.5 * 2.0**-QUANTUM_EXP
    raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")


def default_chunk_models(shard_models: int, levels=DEFAULT_LEVELS) -> int:
    """Models per inner chunk: the models along the last mode (len(levels)) when they tile the shard, else 1."""
    k = len(_levels_array(levels))
    return k if shard_models % k == 0 else 1


# ------------------------------------------------------------------------------------------- create
def vertex_selector(surface_vertex: np.ndarray) -> slice | np.ndarray:
    """``surface_vertex`` as a slice when it is a run of consecutive vertices (the template's: 28,322 ..
    81,093), else as an int64 array: a slice copies memory blocks, a fancy index gathers value by value
    (~5x slower on a 49-model batch)."""
    sv = np.asarray(surface_vertex, dtype=np.int64)
    if len(sv) and sv[-1] - sv[0] == len(sv) - 1 and np.all(np.diff(sv) == 1):
        return slice(int(sv[0]), int(sv[-1]) + 1)
    return sv


def hex_model_points(volume_points: np.ndarray, tri_points: np.ndarray, surface_vertex: np.ndarray) -> np.ndarray:
    """The hex model's nodes (..., n_volume + n_surface, 3) mm: its volume nodes (..., n_volume, 3), then
    the tri vertices ``surface_vertex`` (n_surface,) of tri_points (..., n_tri, 3)."""
    return np.concatenate([volume_points, tri_points[..., vertex_selector(surface_vertex), :]], axis=-2)


def create_store(
    path: str | Path,
    n_tri_nodes: int,
    n_hex_nodes: int,
    n_modes: int = DEFAULT_N_MODES,
    levels=DEFAULT_LEVELS,
    shard_models: int = DEFAULT_SHARD_MODELS,
    attrs: dict | None = None,
    encoding: str = "float32-q10",
    max_abs_mm: float = 512.0,
    chunk_models: int | None = None,
    clevel: int = BLOSC_CLEVEL,
    overwrite: bool = False,
    surface_vertex=None,
) -> zarr.Group:
    """Create the empty cohort store (Zarr v3) with ``weights``, ``tri/points``, ``hex/volume_points`` and
    ``hex/surface_vertex``.

    n_hex_nodes: nodes of the hex model; its last ``len(surface_vertex)`` nodes are the tri vertices
    ``surface_vertex`` (the template's ``surface_vertex``; None: none are shared, every node is stored).
    attrs: extra JSON attributes (e.g. ``ssm_sha256``, ``template_sha256`` from :func:`file_sha256`).
    max_abs_mm: the largest |coordinate| the store accepts (mm).  chunk_models: models per inner chunk
    (default :func:`default_chunk_models`); it must divide shard_models (a Zarr shard is whole chunks).
    clevel: blosc-zstd level of the point arrays.
    """
    for name, n in (("n_tri_nodes", n_tri_nodes), ("n_hex_nodes", n_hex_nodes)):
        if int(n) < 1:
            raise ValueError(f"{name} must be >= 1, got {n}")
    sv = np.zeros(0, np.int32) if surface_vertex is None else np.asarray(surface_vertex)
    if sv.ndim != 1 or not np.issubdtype(sv.dtype, np.integer):
        raise ValueError(f"surface_vertex must be a 1-D integer array of tri vertex ids, got {sv.dtype} {sv.shape}")
    if len(sv) and (sv.min() < 0 or sv.max() >= int(n_tri_nodes)):
        raise ValueError(
            f"surface_vertex must index the {n_tri_nodes} tri vertices, got range [{sv.min()}, {sv.max()}]"
        )
    n_volume = int(n_hex_nodes) - len(sv)
    if n_volume < 1:
        raise ValueError(f"the hex model's {n_hex_nodes} nodes leave no volume node after {len(sv)} surface nodes")
    if encoding not in ENCODINGS:
        raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")
    if not 0 < max_abs_mm < 2.0 ** (24 - QUANTUM_EXP):
        raise ValueError(f"max_abs_mm must be in (0, {2 ** (24 - QUANTUM_EXP)}) mm, got {max_abs_mm}")
    lv = _levels_array(levels)
    total = n_models(n_modes, lv)
    n_sh = n_shards(total, shard_models)
    cm = default_chunk_models(shard_models, lv) if chunk_models is None else int(chunk_models)
    if cm < 1 or shard_models % cm:
        raise ValueError(f"chunk_models={chunk_models} must be >= 1 and divide shard_models={shard_models}")
    blosc, _ = _blosc_codecs(clevel)
    if Path(path).exists() and not overwrite:
        raise ValueError(f"{path} already exists; pass overwrite=True to replace it")
    root = zarr.open_group(str(path), mode="w" if overwrite else "w-", zarr_format=3)
    root.attrs.update(
        {
            **(attrs or {}),
            "format": STORE_FORMAT,
            "units": "mm",
            "weights_units": "SD",
            "n_modes": int(n_modes),
            "levels": [float(v) for v in lv],
            "n_models": int(total),
            "model_id": "sum_i index(w_i in levels) * len(levels)^(n_modes - i), mode 1 most significant",
            "shard_models": int(shard_models),
            "chunk_models": cm,
            "n_shards": int(n_sh),
            "n_hex_nodes": int(n_hex_nodes),
            "hex_model": "node k of the hex model (k+1 of the template deck): hex/volume_points[i][k] for k < "
            "n_volume_nodes, else tri/points[i][hex/surface_vertex[k - n_volume_nodes]]",
            "encoding": encoding,
            "quantum_mm": 2.0**-QUANTUM_EXP if encoding == "float32-q10" else None,
            "max_abs_mm": float(max_abs_mm),
            "error_bound_mm": error_bound_mm(encoding, max_abs_mm),
        }
    )
    root.create_array(
        "weights",
        shape=(total, n_modes),
        chunks=(shard_models, n_modes),
        dtype="f8",
        compressors=[ZstdCodec(level=3)],
        fill_value=np.nan,
        dimension_names=("model", "mode"),
    )
    for name, n in (("tri/points", n_tri_nodes), ("hex/volume_points", n_volume)):
        a = root.create_array(
            name,
            shape=(total, int(n), 3),
            chunks=(cm, int(n), 3),
            shards=(shard_models, int(n), 3),
            dtype="f4",
            filters=[TransposeCodec(order=CHUNK_ORDER)],
            compressors=[blosc],
            fill_value=0.0,
            dimension_names=("model", "node", "xyz"),
        )
        a.attrs.update({"units": "mm"})
    a = root.create_array(
        SURFACE_VERTEX,
        shape=(len(sv),),
        chunks=(max(len(sv), 1),),
        dtype="i4",
        compressors=[ZstdCodec(level=3)],
        fill_value=-1,
        dimension_names=("surface_node",),
    )
    if len(sv):
        a[:] = sv.astype(np.int32)
    a.attrs.update({"about": "tri vertex of each hex-model node after the volume nodes (0-based)"})
    root.create_group(
        _CHECKSUM_DIR,
        attributes={"about": "one subgroup per finished shard; attributes hold crc32c and size of its stored objects"},
    )
    return root


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file (for the SSM/template checksums recorded in the store attributes)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def crc32c_hex(crc: int) -> str:
    """A crc32c value as the shard records write it: 8 lowercase hex digits."""
    return f"{crc & 0xFFFFFFFF:08x}"


def object_crc32c(path: str | Path) -> str:
    """crc32c (Castagnoli, the checksum of Zarr's ``crc32c`` codec and of the shard index) of a shard object,
    as :func:`crc32c_hex`, read with ``O_DIRECT`` like :func:`object_sha256`.

    The shard records hold crc32c, not sha256 (format 4; docs/store.md "Shard checksums"): they detect
    corruption and interrupted writes, which a 32-bit CRC does (every burst up to 32 bits, any other change
    but for 2^-32), at ~5 GB/s instead of sha256's ~1.1 GB/s on this machine; tampering is the release's
    concern, whose BagIt manifests hold sha256."""
    crc = 0
    with DirectReader(path) as r:
        for block in r.blocks():
            # the C extension refuses a memoryview of the (writable) read buffer but takes a numpy view of it: no
            # copy of the 8 GB the check reads (1.3 instead of 2.1 s of CPU for the default store)
            crc = google_crc32c.extend(crc, np.frombuffer(block, np.uint8))
    return crc32c_hex(crc)


def object_sha256(path: str | Path) -> str:
    """Hex sha256 of a shard object, read with ``O_DIRECT`` (:class:`DirectReader`: around the page cache, as
    :class:`DirectWriter` wrote it, the next buffer read by a thread while this one is hashed).  The same
    digest as :func:`file_sha256`.  A cold buffered read of the 12.9 GB store cost ~21 s of kernel CPU for its
    page-cache pages, this ~1 s (docs/store.md)."""
    h = hashlib.sha256()
    with DirectReader(path) as r:
        for block in r.blocks():
            h.update(block)
    return h.hexdigest()


class DirectReader:
    """Read one file sequentially with ``O_DIRECT`` (around the page cache, as :class:`DirectWriter` wrote
    it): ``blocks()`` yields it buffer by buffer without a copy (`object_sha256`), ``read(n)`` is a binary file
    object's (the release tars the store with it, which would otherwise pay the kernel ~21-29 s of CPU for the
    page-cache pages of 12.9 GB it reads once; docs/store.md).  Two page-aligned buffers of
    ``DirectWriter.BUFFER`` bytes, the next one read by a thread while the caller uses this one (``readv``
    releases the GIL); the tail after a short read (end of file, unaligned) and any file system that refuses
    ``O_DIRECT`` (at the open or the first read) go by ordinary reads."""

    def __init__(self, path: str | Path):
        from concurrent.futures import ThreadPoolExecutor

        self._path, self._fd, self._file = Path(path), -1, None
        self._bufs = [mmap.mmap(-1, DirectWriter.BUFFER) for _ in range(2)]
        self._views = [memoryview(b) for b in self._bufs]
        self._cur, self._start, self._end = 0, 0, 0  # unread bytes: views[cur][start:end]
        self._done = 0  # file bytes read into the buffers so far
        self._pool, self._ahead = ThreadPoolExecutor(1), None
        try:
            self._fd = os.open(self._path, os.O_RDONLY | os.O_DIRECT)
        except (AttributeError, OSError) as e:
            if isinstance(e, OSError) and e.errno != errno.EINVAL:
                raise
            self._file = open(self._path, "rb")

    def _buffered_from(self, offset: int) -> None:
        os.close(self._fd)
        self._fd = -1
        self._file = open(self._path, "rb")
        self._file.seek(offset)

    def _fill(self) -> None:
        """Make the next buffer current (read ahead, or now); after a short read the rest goes buffered."""
        nxt = 1 - self._cur if self._ahead is not None else self._cur
        try:
            n = self._ahead.result() if self._ahead is not None else os.readv(self._fd, [self._bufs[nxt]])
        except OSError as e:
            if e.errno != errno.EINVAL:
                raise
            self._ahead = None
            self._buffered_from(self._done)  # the flag was taken but the I/O refused
            return
        self._ahead = None
        self._cur, self._start, self._end = nxt, 0, n
        self._done += n
        if n == DirectWriter.BUFFER:
            self._ahead = self._pool.submit(os.readv, self._fd, [self._bufs[1 - nxt]])
        else:  # end of file (or a short read): anything after it, buffered
            self._buffered_from(self._done)

    def blocks(self):
        """The file's bytes as consecutive memoryviews, each valid until the next one is asked for."""
        while True:
            if self._start < self._end:
                view = self._views[self._cur][self._start : self._end]
                self._start = self._end
                try:
                    yield view
                finally:
                    view.release()  # the buffer is read into again, and closing it needs no view left
            elif self._file is not None:
                yield from iter(lambda: self._file.read(DirectWriter.BUFFER), b"")
                return
            else:
                self._fill()

    def read(self, size: int = -1) -> bytes:
        out, got = [], 0
        while size is None or size < 0 or got < size:
            if self._start < self._end:
                k = self._end - self._start if size is None or size < 0 else min(size - got, self._end - self._start)
                out.append(bytes(self._views[self._cur][self._start : self._start + k]))
                self._start += k
                got += k
            elif self._file is not None:
                out.append(self._file.read(-1 if size is None or size < 0 else size - got))
                break
            else:
                self._fill()
        return b"".join(out)

    def close(self) -> None:
        if self._ahead is not None:
            self._ahead.exception()  # let the read in flight finish before its buffer goes
            self._ahead = None
        self._pool.shutdown()
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        if self._file is not None:
            self._file.close()
        for v, b in zip(self._views, self._bufs):
            if not b.closed:
                v.release()
                b.close()

    def __enter__(self) -> DirectReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -------------------------------------------------------------------------------------------- write
def _shard_objects(path: Path, shard: int) -> list[Path]:
    """Files holding shard ``shard``: the two point shards and the weights chunk (default key encoding)."""
    return [
        path / "tri/points/c" / str(shard) / "0" / "0",
        path / "hex/volume_points/c" / str(shard) / "0" / "0",
        path / "weights/c" / str(shard) / "0",
    ]


def _sidecar(shard: int) -> str:
    return f"{_CHECKSUM_DIR}/shard_{shard:05d}"


def _open_meta(path: str | Path) -> tuple[zarr.Group, dict]:
    p = Path(path)
    if not (p / "zarr.json").is_file():
        raise ValueError(f"{p} is not a cohort store (no zarr.json); create it with create_store")
    # the root zarr.json alone: opening the group would parse the arrays' metadata too, which fails on
    # codecs an older version used
    meta = json.loads((p / "zarr.json").read_text()).get("attributes", {})
    fmt = meta.get("format")
    if fmt != STORE_FORMAT:
        if isinstance(fmt, str) and fmt.startswith(_FORMAT_PREFIX):
            raise StoreVersionError(
                f"{p} was written by another spinecohort version (format {fmt!r}, this version reads "
                f"{STORE_FORMAT!r}); it cannot be read correctly. Rebuild it: "
                f"remove {p} and the shard records (results/shards/), then run snakemake again"
            )
        raise ValueError(f"{p} is not a spinecohort cohort store (format {fmt!r})")
    return zarr.open_group(str(p), mode="r"), meta


def _check_coordinates(name: str, shard: int, x: np.ndarray, max_abs_mm: float) -> None:
    lo, hi = float(x.min()), float(x.max())  # NaN propagates; no temporaries on large batches
    _check_range(name, shard, lo, hi, bool(np.isfinite(lo) and np.isfinite(hi)), max_abs_mm)


def _span(values: np.ndarray) -> tuple[float, float, bool]:
    """(min, max, all finite) of stored values, for the error message of :func:`_check_range`."""
    finite = np.isfinite(values)
    ok = values[finite]
    return float(ok.min(initial=np.inf)), float(ok.max(initial=-np.inf)), bool(finite.all())


def _check_range(name: str, shard: int, lo: float, hi: float, finite: bool, max_abs_mm: float) -> None:
    if not finite:
        raise ValueError(f"{name} of shard {shard} has non-finite coordinates")
    if max(-lo, hi) > max_abs_mm:
        raise ValueError(
            f"{name} of shard {shard} exceeds the store's max_abs_mm={max_abs_mm} "
            f"(coordinates span [{lo:.1f}, {hi:.1f}] mm)"
        )


def check_surface_nodes(tri: np.ndarray, hexp: np.ndarray, surface_vertex: np.ndarray, encoding: str, first_id: int):
    """Raise ValueError unless the last ``len(surface_vertex)`` nodes of the hex models hexp (B, n_hex, 3) mm
    round to the stored values of their tri vertices in tri (B, n_tri, 3) mm (the store keeps them once)."""
    sv = np.asarray(surface_vertex)
    n_vol = hexp.shape[1] - len(sv)
    sel = vertex_selector(sv)
    for k in range(len(hexp)):  # one model at a time: no shard-sized temporaries
        diff = (quantize_mm(hexp[k, n_vol:], encoding) != quantize_mm(tri[k, sel], encoding)).any(axis=1)
        if diff.any():
            node = n_vol + int(np.flatnonzero(diff)[0])
            raise ValueError(
                f"{model_name(first_id + k)}: hex node {node} is not its tri vertex {int(sv[node - n_vol])} as "
                f"stored ({int(diff.sum())} surface nodes differ); the store keeps each surface node once, in "
                "tri/points (hex/surface_vertex)"
            )


class DirectWriter:
    """Write one new file sequentially with ``O_DIRECT``: around the page cache (docs/store.md, "Writing the
    shard files"), for the shard objects, which no job reads back.

    Buffered writes of a 1.84 GB shard cost the writing process seconds of kernel CPU for page-cache pages
    (more when memory is full and the kernel must reclaim to find them) and leave the pages cached; here the
    bytes go through one page-aligned ``mmap`` buffer of ``BUFFER`` bytes (a whole-buffer ``write`` each
    time it fills) straight to the disk.  ``close()`` writes the last partial buffer padded with zeros to
    ``ALIGN`` bytes and truncates the file to the bytes given: the file holds exactly what was written.  A
    file system that refuses ``O_DIRECT`` (``EINVAL`` at the open or the first write: tmpfs before Linux 6.6,
    some network and FUSE file systems) gets the same bytes by ordinary writes (``direct`` is then False).
    """

    BUFFER = 8 << 20
    #: O_DIRECT's alignment of buffer address, file offset and length (>= any logical block size here)
    ALIGN = 4096

    def __init__(self, path: str | Path):
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
        self.direct = hasattr(os, "O_DIRECT")
        try:
            self._fd = os.open(path, flags | (os.O_DIRECT if self.direct else 0), 0o666)
        except OSError as e:
            if e.errno != errno.EINVAL:
                raise
            self.direct = False
            self._fd = os.open(path, flags, 0o666)
        self._buf = mmap.mmap(-1, self.BUFFER)
        self._view = memoryview(self._buf)
        self._pos = 0
        self.size = 0

    def write(self, data) -> int:
        src = memoryview(data).cast("B")
        n, i = len(src), 0
        while i < n:
            k = min(n - i, self.BUFFER - self._pos)
            self._view[self._pos : self._pos + k] = src[i : i + k]
            self._pos += k
            i += k
            if self._pos == self.BUFFER:
                self._flush(self.BUFFER)
        self.size += n
        return n

    def _flush(self, n: int) -> None:
        done = 0
        while done < n:
            try:
                done += os.write(self._fd, self._view[done:n])
            except OSError as e:
                if e.errno != errno.EINVAL or not self.direct or done:
                    raise
                # the file system took the open flag but refuses the I/O: the same bytes, buffered
                fcntl.fcntl(self._fd, fcntl.F_SETFL, fcntl.fcntl(self._fd, fcntl.F_GETFL) & ~os.O_DIRECT)
                self.direct = False
        self._pos = 0

    def close(self) -> None:
        if self._fd < 0:
            return
        try:
            tail = self._pos
            if tail:
                n = -(-tail // self.ALIGN) * self.ALIGN if self.direct else tail
                self._view[tail:n] = bytes(n - tail)
                self._flush(n)
                if n != tail:  # drop the zero padding
                    os.ftruncate(self._fd, self.size)
        finally:
            os.close(self._fd)
            self._fd = -1
            self._view.release()
            self._buf.close()

    def __del__(self) -> None:
        if getattr(self, "_fd", -1) >= 0:
            self.close()

    def __enter__(self) -> DirectWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ShardWriter:
    """Write shard ``shard`` of both point arrays batch by batch, then its weights and its sidecar.

    ``add(tri, hex)`` takes the next models of the shard in ID order (mm, any float dtype; batches a multiple
    of ``chunk_models`` except the last): tri (B, n_tri, 3) and hex either the volume nodes (B, n_volume, 3)
    or the whole hex model (B, n_hex_nodes, 3), whose surface nodes must then round to the stored values of
    their tri vertices (else ValueError: the store could not give them back).  It rounds them as stored,
    encodes each inner chunk (transpose, blosc)
    and appends it to ``<object>.<pid>.partial``; ``close()`` appends the shard index (offset and nbytes per
    chunk, uint64 little-endian, then its crc32c), moves the objects into place (rename: atomic), writes the
    weights and last the checksum sidecar, the shard's completion mark.  A writer that is not closed
    leaves no sidecar; the next writer of the shard removes the leftovers first.
    """

    def __init__(self, path: str | Path, shard: int):
        self.path = Path(path)
        root, meta = _open_meta(self.path)
        self.meta, self.shard = meta, int(shard)
        self.start, self.stop = shard_range(self.shard, meta["shard_models"], meta["n_models"])
        self.chunk = int(meta["chunk_models"])
        self.n_nodes = {name: root[name].shape[1] for name in POINT_ARRAYS}
        self.surface_vertex = np.asarray(root[SURFACE_VERTEX][:], dtype=np.int64)
        self.n_hex_nodes = int(meta["n_hex_nodes"])
        clevel = root["tri/points"].metadata.codecs[0].codecs[-1].clevel  # sharding -> inner chain -> blosc
        self._codec = _blosc_codecs(clevel)[1]
        self._clear()
        self.objects = dict(zip(POINT_ARRAYS, _shard_objects(self.path, self.shard)[:2]))
        self._tmp, self._files, self._index, self._crc, self._offset = {}, {}, {}, {}, {}
        for name, obj in self.objects.items():
            obj.parent.mkdir(parents=True, exist_ok=True)
            self._tmp[name] = obj.with_name(f"{obj.name}.{os.getpid()}.partial")
            self._files[name] = DirectWriter(self._tmp[name])  # around the page cache: no job reads it back
            slots = meta["shard_models"] // self.chunk
            self._index[name] = np.full((slots, 2), _EMPTY, dtype="<u8")
            self._crc[name] = 0
            self._offset[name] = 0
        self._buffers = {}  # per array: float32 stored-order chunks of the largest batch so far
        self._scratch = (
            np.empty((self.chunk, _LINEAR_BLOCK), np.float32),
            np.empty(_LINEAR_BLOCK),
            np.empty(_LINEAR_BLOCK),
        )
        self.n_written = 0
        self.encode_cpu_s = 0.0  # CPU time in the codec alone (the benchmark's compression floor)
        self.stored_bytes = 0

    def _clear(self) -> None:
        """Remove the sidecar (a rewrite is incomplete until its new one lands), the shard's objects and
        any ``*.partial`` of a killed writer: zarr would otherwise read a stale index."""
        side = self.path / _sidecar(self.shard)
        if side.exists():
            for f in side.iterdir():
                f.unlink()
            side.rmdir()
        for obj in _shard_objects(self.path, self.shard):
            obj.unlink(missing_ok=True)
            if obj.parent.is_dir():
                for stale in obj.parent.glob(obj.name + ".*.partial"):
                    stale.unlink()

    def add(self, tri, hexp) -> None:
        """Append the next models: tri (B, n_tri, 3) mm, hex (B, n_volume, 3) or (B, n_hex_nodes, 3) mm; either
        may be a :class:`LinearPoints` (its chunks are formed in stored order as they are encoded)."""
        if not isinstance(tri, LinearPoints):
            tri = np.asarray(tri)
        if not isinstance(hexp, LinearPoints):
            hexp = np.asarray(hexp)
        n_vol = self.n_nodes["hex/volume_points"]
        if hexp.shape[1] == self.n_hex_nodes and self.n_hex_nodes != n_vol:
            if isinstance(tri, LinearPoints) or isinstance(hexp, LinearPoints):
                raise ValueError("the whole hex model is checked against float tri points: pass the volume nodes")
            self._check_surface(tri, hexp)
            hexp = hexp[:, :n_vol]
        batch = {"tri/points": tri, "hex/volume_points": hexp}
        b = len(tri)
        if len(hexp) != b:
            raise ValueError(f"tri and hex batches differ in models: {b} vs {len(hexp)}")
        if self.start + self.n_written + b > self.stop:
            raise ValueError(f"shard {self.shard} holds {self.stop - self.start} models; got {self.n_written + b}")
        if self.n_written % self.chunk:
            raise ValueError(f"only the last batch may be a partial chunk of {self.chunk} models")
        n_chunks = -(-b // self.chunk)  # a partial last chunk is the array's boundary chunk, zero-filled
        quantize = self.meta["encoding"] == "float32-q10"
        values = {}
        for name, x in batch.items():  # every chunk of the batch is formed and checked before any is encoded
            want = (self.n_nodes[name], 3)
            if len(x.shape) != 3 or x.shape[1:] != want:
                raise ValueError(f"{name} of shard {self.shard} must have shape (models, {want[0]}, 3), got {x.shape}")
            values[name] = self._buffer(name, n_chunks)
            if isinstance(x, LinearPoints):  # all chunks in one pass over the formula's terms
                if x.stored_chunks(quantize, self.meta["max_abs_mm"], values[name], self._scratch):
                    _check_range(name, self.shard, *_span(values[name]), self.meta["max_abs_mm"])
                continue
            if not np.issubdtype(x.dtype, np.floating):
                x = x.astype(np.float64)
            lo, hi, finite = _stored_chunks_nb(x, quantize, self.chunk, values[name])
            # checked on the stored float32 values (NaN and inf survive the rounding)
            _check_range(name, self.shard, lo, hi, finite, self.meta["max_abs_mm"])
        first_slot = self.n_written // self.chunk
        for name in batch:
            for j, c in enumerate(values[name]):  # c: one inner chunk, already in stored order
                self._append(name, first_slot + j, c)
        self.n_written += b

    def _buffer(self, name: str, n_chunks: int) -> np.ndarray:
        """(n_chunks, 3, nodes, chunk) float32 stored-order chunks of ``name``, reused batch after batch."""
        buf = self._buffers.get(name)
        if buf is None or len(buf) < n_chunks:
            buf = self._buffers[name] = np.empty((n_chunks, 3, self.n_nodes[name], self.chunk), np.float32)
        return buf[:n_chunks]

    def _append(self, name: str, slot: int, chunk: np.ndarray) -> None:
        """Encode one inner chunk (stored order) and append it to the array's shard object."""
        t0 = time.process_time()
        data = self._codec.encode(chunk)
        self.encode_cpu_s += time.process_time() - t0
        self._index[name][slot] = (self._offset[name], len(data))
        self._files[name].write(data)
        self._crc[name] = google_crc32c.extend(self._crc[name], data)
        self._offset[name] += len(data)

    def _check_surface(self, tri: np.ndarray, hexp: np.ndarray) -> None:
        if tri.ndim != 3 or len(tri) != len(hexp) or tri.shape[1] != self.n_nodes["tri/points"]:
            raise ValueError(
                f"tri/points of shard {self.shard} must have shape (models, {self.n_nodes['tri/points']}, 3)"
            )
        check_surface_nodes(tri, hexp, self.surface_vertex, self.meta["encoding"], self.start + self.n_written)

    def close(self) -> dict:
        """Finish the shard (index, rename, weights, sidecar); returns the sidecar record."""
        if self.start + self.n_written != self.stop:
            self.abort()
            raise ValueError(f"shard {self.shard} got {self.n_written} of its {self.stop - self.start} models")
        objects = {}
        for name, obj in self.objects.items():
            index = self._index[name].tobytes()
            tail = index + np.uint32(google_crc32c.value(index)).astype("<u4").tobytes()
            self._files[name].write(tail)
            self._crc[name] = google_crc32c.extend(self._crc[name], tail)
            self._files[name].close()
            os.replace(self._tmp[name], obj)
            objects[str(obj.relative_to(self.path))] = {
                "crc32c": crc32c_hex(self._crc[name]),
                "bytes": obj.stat().st_size,
            }
            self.stored_bytes += obj.stat().st_size
            if os.environ.get(FAULT_KILL_ENV) == str(self.shard):  # fault injection: die between the two arrays
                os.kill(os.getpid(), signal.SIGKILL)
        rw = zarr.open_group(str(self.path), mode="r+")
        rw["weights"][self.start : self.stop] = weights_of(
            np.arange(self.start, self.stop), self.meta["n_modes"], self.meta["levels"]
        )
        w_obj = _shard_objects(self.path, self.shard)[2]
        objects[str(w_obj.relative_to(self.path))] = {
            "crc32c": crc32c_hex(google_crc32c.value(w_obj.read_bytes())),
            "bytes": w_obj.stat().st_size,
        }
        record = {"shard": self.shard, "models": [self.start, self.stop], "objects": objects}
        # zarr's LocalStore writes zarr.json through a temporary file and a rename: atomic on POSIX
        zarr.create_group(str(self.path), path=_sidecar(self.shard), attributes=record, zarr_format=3)
        return record

    def abort(self) -> None:
        """Drop what was written (the shard then reads as never written)."""
        for name, f in self._files.items():
            f.close()
            self._tmp[name].unlink(missing_ok=True)


def write_shard(path: str | Path, shard: int, tri_points: np.ndarray, hex_points: np.ndarray) -> dict:
    """Write shard ``shard`` whole: tri_points (S, n_tri_nodes, 3), hex_points (S, n_hex_nodes, 3) (the whole
    hex model) or (S, n_volume_nodes, 3) in mm, S = models in the shard.  Returns the sidecar record (see
    :class:`ShardWriter`)."""
    tri, hexp = np.asarray(tri_points), np.asarray(hex_points)
    root, meta = _open_meta(path)
    start, stop = shard_range(int(shard), meta["shard_models"], meta["n_models"])
    n_vol = root["hex/volume_points"].shape[1]
    for name, x, n in (
        ("tri/points", tri, (root["tri/points"].shape[1],)),
        ("hex points", hexp, tuple(sorted({meta["n_hex_nodes"], n_vol}))),
    ):
        if x.ndim != 3 or len(x) != stop - start or x.shape[1] not in n or x.shape[2] != 3:
            nodes = " or ".join(str(k) for k in n)
            raise ValueError(f"{name} of shard {shard} must have shape ({stop - start}, {nodes}, 3), got {x.shape}")
        _check_coordinates(name, shard, x, meta["max_abs_mm"])  # before the writer clears the old shard
    if hexp.shape[1] != n_vol:  # the whole hex model: its surface nodes must be the tri vertices
        sv = root[SURFACE_VERTEX][:]
        check_surface_nodes(tri, hexp, sv, meta["encoding"], start)
        hexp = hexp[:, :n_vol]
    writer = ShardWriter(path, shard)
    try:
        writer.add(tri, hexp)
    except BaseException:
        writer.abort()
        raise
    return writer.close()


# --------------------------------------------------------------------------------------------- read
def read_model(path: str | Path, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(tri (n_tri_nodes, 3), hex (n_hex_nodes, 3): the whole hex model, :func:`hex_model_points`) float32
    node coordinates in mm of model ``i``."""
    root, meta = _open_meta(path)
    if not 0 <= int(i) < meta["n_models"]:
        raise ValueError(f"model {i} out of range [0, {meta['n_models']})")
    tri = root["tri/points"][int(i)]
    return tri, hex_model_points(root["hex/volume_points"][int(i)], tri, root[SURFACE_VERTEX][:])


#: what read_shard reads: a stored array, or "hex", the whole hex model assembled from both
SHARD_ARRAYS = (*POINT_ARRAYS, "hex")


def read_shard(path: str | Path, shard: int, array: str = "tri/points") -> np.ndarray:
    """Node coordinates (S, n_nodes, 3) float32 mm of all models of ``shard``: a stored point array, or
    ``"hex"``, the whole hex model (:func:`hex_model_points`)."""
    if array not in SHARD_ARRAYS:
        raise ValueError(f"array must be one of {SHARD_ARRAYS}, got {array!r}")
    root, meta = _open_meta(path)
    start, stop = shard_range(int(shard), meta["shard_models"], meta["n_models"])
    if array == "hex":
        return hex_model_points(
            root["hex/volume_points"][start:stop], root["tri/points"][start:stop], root[SURFACE_VERTEX][:]
        )
    return root[array][start:stop]


def shard_problems(path: str | Path) -> dict[int, str]:
    """Shards that must be (re)written, with why: no sidecar (never finished, or killed), a missing
    object, or an object whose size or crc32c differs from the one recorded when it was written."""
    p = Path(path)
    _, meta = _open_meta(p)
    bad = {}
    for s in range(meta["n_shards"]):
        side = p / _sidecar(s) / "zarr.json"
        if not side.is_file():
            bad[s] = "no checksum record (never written, or its job was killed before it finished)"
            continue
        rec = json.loads(side.read_text())["attributes"]
        for rel, want in rec["objects"].items():
            obj = p / rel
            if not obj.is_file():
                bad[s] = f"{rel} is missing"
            elif obj.stat().st_size != want["bytes"]:
                bad[s] = f"{rel} has {obj.stat().st_size} bytes, {want['bytes']} were written"
            elif object_crc32c(obj) != want["crc32c"]:
                bad[s] = f"{rel} is corrupt (crc32c differs from the one recorded at write time)"
            if s in bad:
                break
    return bad


def check_store(path: str | Path) -> list[int]:
    """Shards that must be (re)written (``shard_problems`` without the reasons)."""
    return sorted(shard_problems(path))


def invalidate_shard(path: str | Path, shard: int) -> list[Path]:
    """Remove shard ``shard``'s checksum record and data objects, so that it reads as never written and
    its next ``write_shard`` starts from nothing.  Returns the files removed."""
    p = Path(path)
    _open_meta(p)
    removed = []
    side = p / _sidecar(shard)
    if side.is_dir():
        for f in side.iterdir():
            f.unlink()
            removed.append(f)
        side.rmdir()
    for obj in _shard_objects(p, shard):
        if obj.is_file():
            obj.unlink()
            removed.append(obj)
    return removed
