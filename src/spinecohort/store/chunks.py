"""The store's chunk-forming kernels: a batch of models into inner chunks in stored order, one numba pass.

The writer hands the codec each inner chunk already as stored: the ``CHUNK_ORDER`` transpose (coordinate,
node, model) of the chunk's values rounded as :func:`spinecohort.store.format.quantize_mm` rounds them.
:func:`_stored_chunks_nb` does that for float coordinates; :class:`LinearPoints` forms the chunks straight
from the SSM's linear formula (``mean + sum_i w_i fields[i]``, plus the disc-contact translations), so the
float64 coordinates of the 81k-vertex triangulated models never exist as a batch.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _stored_value_nb(x, quantize):
    """The stored float32 value of one coordinate x mm: with ``quantize`` = 2^k > 0, :func:`quantize_mm`'s
    rounding to 2^-k mm in float64 (then exact in float32); with 0.0 the nearest float32."""
    if quantize > 0.0:
        return np.float32(np.rint(x * quantize)) * np.float32(1.0 / quantize)
    return np.float32(x)


@numba.njit(cache=True)
def _stored_chunks_nb(x, quantize, chunk, out):
    """The stored values of a batch x (B, N, 3) mm, chunk by chunk in stored order: out (K, 3, N, chunk)
    float32 with out[k, c, n, m] = value of model k * chunk + m, node n, coordinate c (``CHUNK_ORDER``);
    models past B are 0 (the boundary chunk's fill value).  quantize = 2^k: rint(x * 2^k) / 2^k in float64,
    cast to float32 (exact, see :func:`quantize_mm`); 0.0: the nearest float32.  Returns (min, max, all
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

    def stored_chunks(self, quantize: float, max_abs_mm: float, out: np.ndarray, scratch) -> int:
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
