"""The compiled (numba) quality kernels: per element, per mesh and per batch of models.

Each loops over the elements of a contiguous X (n_nodes, 3) and conn (E, 8) and computes the numbers of the
numpy definitions in `spinecohort.mesh.quality.verdict` (tested to agree): the scaled Jacobian alone
(``min_scaled_jacobian_nb``, fused with the morph in ``morph_scaled_jacobian_nb``), all seven metrics
(``full_metrics_nb``), the Bernstein bounds of det J (``bernstein_bounds_nb``, for
`spinecohort.mesh.quality.certificate`), and the shard pass's check + Table 3 of a batch vectorised across
the models (``model_quality_lanes_nb``).  Helpers that the kernels inline live here too, so that numba's
cache (keyed by this file) recompiles every kernel that uses them when one changes.
"""

from __future__ import annotations

import numba
import numpy as np

from spinecohort.mesh.quality.element import (
    CORNER_NEIGHBOURS,
    DN_CENTRE,
    DN_GAUSS,
    DN_HALF,
    GAUSS_1D,
    HEX_EDGES,
    HEX_FACES,
    LAGRANGE_TO_BERNSTEIN,
    VERDICT_DBL_MAX,
    VERDICT_DBL_MIN,
)

_CN = CORNER_NEIGHBOURS
_EDGES = HEX_EDGES
_FACES = HEX_FACES


@numba.njit(cache=True, inline="always")
def _det3_nb(a0, a1, a2, b0, b1, b2, c0, c1, c2):
    return a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)


@numba.njit(cache=True, inline="always")
def _centre_sj_nb(P):
    """(ok, scaled Jacobian at the element centre) of P (8, 3): the determinant of the three principal axes
    (sums of the four parallel edges) over their lengths; ok False when an axis is degenerate."""
    x10 = (P[1, 0] - P[0, 0]) + (P[2, 0] - P[3, 0]) + (P[5, 0] - P[4, 0]) + (P[6, 0] - P[7, 0])
    x11 = (P[1, 1] - P[0, 1]) + (P[2, 1] - P[3, 1]) + (P[5, 1] - P[4, 1]) + (P[6, 1] - P[7, 1])
    x12 = (P[1, 2] - P[0, 2]) + (P[2, 2] - P[3, 2]) + (P[5, 2] - P[4, 2]) + (P[6, 2] - P[7, 2])
    x20 = (P[3, 0] - P[0, 0]) + (P[2, 0] - P[1, 0]) + (P[7, 0] - P[4, 0]) + (P[6, 0] - P[5, 0])
    x21 = (P[3, 1] - P[0, 1]) + (P[2, 1] - P[1, 1]) + (P[7, 1] - P[4, 1]) + (P[6, 1] - P[5, 1])
    x22 = (P[3, 2] - P[0, 2]) + (P[2, 2] - P[1, 2]) + (P[7, 2] - P[4, 2]) + (P[6, 2] - P[5, 2])
    x30 = (P[4, 0] - P[0, 0]) + (P[5, 0] - P[1, 0]) + (P[6, 0] - P[2, 0]) + (P[7, 0] - P[3, 0])
    x31 = (P[4, 1] - P[0, 1]) + (P[5, 1] - P[1, 1]) + (P[6, 1] - P[2, 1]) + (P[7, 1] - P[3, 1])
    x32 = (P[4, 2] - P[0, 2]) + (P[5, 2] - P[1, 2]) + (P[6, 2] - P[2, 2]) + (P[7, 2] - P[3, 2])
    l1 = x10 * x10 + x11 * x11 + x12 * x12
    l2 = x20 * x20 + x21 * x21 + x22 * x22
    l3 = x30 * x30 + x31 * x31 + x32 * x32
    if l1 <= VERDICT_DBL_MIN or l2 <= VERDICT_DBL_MIN or l3 <= VERDICT_DBL_MIN:
        return False, 0.0
    return True, _det3_nb(x10, x11, x12, x20, x21, x22, x30, x31, x32) / np.sqrt(l1 * l2 * l3)


@numba.njit(cache=True)
def _element_min_sj_nb(P, cn):
    """Scaled Jacobian of one element P (8, 3) (same rules as _scaled_jacobian_P)."""
    sj = VERDICT_DBL_MAX
    for i in range(8):
        a, b, c = cn[i, 0], cn[i, 1], cn[i, 2]
        a0, a1, a2 = P[a, 0] - P[i, 0], P[a, 1] - P[i, 1], P[a, 2] - P[i, 2]
        b0, b1, b2 = P[b, 0] - P[i, 0], P[b, 1] - P[i, 1], P[b, 2] - P[i, 2]
        c0, c1, c2 = P[c, 0] - P[i, 0], P[c, 1] - P[i, 1], P[c, 2] - P[i, 2]
        la = a0 * a0 + a1 * a1 + a2 * a2
        lb = b0 * b0 + b1 * b1 + b2 * b2
        lc = c0 * c0 + c1 * c1 + c2 * c2
        if la <= VERDICT_DBL_MIN or lb <= VERDICT_DBL_MIN or lc <= VERDICT_DBL_MIN:
            return VERDICT_DBL_MAX
        s = _det3_nb(a0, a1, a2, b0, b1, b2, c0, c1, c2) / np.sqrt(la * lb * lc)
        sj = min(sj, s)
    ok, centre = _centre_sj_nb(P)
    if not ok:
        return VERDICT_DBL_MAX
    return min(sj, centre)


@numba.njit(cache=True)
def min_scaled_jacobian_nb(X, conn):
    """Scaled Jacobian per element from X (n_nodes, 3) float64 and conn (E, 8) int64 -> (E,)."""
    out = np.empty(conn.shape[0])
    P = np.empty((8, 3))
    for e in range(conn.shape[0]):
        for k in range(8):
            for d in range(3):
                P[k, d] = X[conn[e, k], d]
        out[e] = _element_min_sj_nb(P, _CN)
    return out


@numba.njit(cache=True)
def morph_scaled_jacobian_nb(mean_points, modes, weights, conn):
    """Fused morph + check: for each sample b, X = mean + sum_i w_bi * mode_i, then scaled Jacobian per element.

    mean_points (N, 3), modes (M, N, 3), weights (B, M) -> (B, E). Never holds more than one X in memory.
    """
    B, M = weights.shape
    N = mean_points.shape[0]
    out = np.empty((B, conn.shape[0]))
    X = np.empty((N, 3))
    for b in range(B):
        for n in range(N):
            for d in range(3):
                X[n, d] = mean_points[n, d]
        for i in range(M):
            w = weights[b, i]
            for n in range(N):
                for d in range(3):
                    X[n, d] += w * modes[i, n, d]
        out[b] = min_scaled_jacobian_nb(X, conn)
    return out


@numba.njit(cache=True)
def _detj_nb(P, dN):
    """det J at one parametric point given dN (8, 3). Scalars, not a 3x3 array: no heap allocation."""
    j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
    for n in range(8):
        px, py, pz = P[n, 0], P[n, 1], P[n, 2]
        du, dv, dw = dN[n, 0], dN[n, 1], dN[n, 2]
        j00 += du * px
        j01 += du * py
        j02 += du * pz
        j10 += dv * px
        j11 += dv * py
        j12 += dv * pz
        j20 += dw * px
        j21 += dw * py
        j22 += dw * pz
    return _det3_nb(j00, j01, j02, j10, j11, j12, j20, j21, j22)


@numba.njit(cache=True)
def full_metrics_nb(X, conn):
    """Per element: [scaled J, Verdict J, nodal J ratio, Gauss J ratio, edge ratio, min angle, max angle] -> (E, 7)."""
    E = conn.shape[0]
    out = np.empty((E, 7))
    P = np.empty((8, 3))
    dNg = DN_GAUSS
    for e in range(E):
        for k in range(8):
            for d in range(3):
                P[k, d] = X[conn[e, k], d]
        out[e, 0] = _element_min_sj_nb(P, _CN)
        amin, amax = np.inf, -np.inf
        for i in range(8):
            a, b, c = _CN[i, 0], _CN[i, 1], _CN[i, 2]
            al = _det3_nb(
                P[a, 0] - P[i, 0],
                P[a, 1] - P[i, 1],
                P[a, 2] - P[i, 2],
                P[b, 0] - P[i, 0],
                P[b, 1] - P[i, 1],
                P[b, 2] - P[i, 2],
                P[c, 0] - P[i, 0],
                P[c, 1] - P[i, 1],
                P[c, 2] - P[i, 2],
            )
            amin = min(amin, al)
            amax = max(amax, al)
        d8 = _detj_nb(P, DN_CENTRE) * 64.0  # principal axes = 4 dX/du etc. at the centre
        out[e, 1] = min(amin, d8 / 64.0)
        out[e, 2] = -VERDICT_DBL_MAX if amax <= VERDICT_DBL_MIN else amin / amax
        gmin, gmax = np.inf, -np.inf
        for q in range(8):
            g = _detj_nb(P, dNg[q])
            gmin = min(gmin, g)
            gmax = max(gmax, g)
        out[e, 3] = -VERDICT_DBL_MAX if gmax <= VERDICT_DBL_MIN else gmin / gmax
        lmin, lmax = np.inf, 0.0
        for k in range(12):
            i, j = _EDGES[k, 0], _EDGES[k, 1]
            L = (P[j, 0] - P[i, 0]) ** 2 + (P[j, 1] - P[i, 1]) ** 2 + (P[j, 2] - P[i, 2]) ** 2
            lmin = min(lmin, L)
            lmax = max(lmax, L)
        out[e, 4] = np.sqrt(lmax / lmin) if lmin > 0 else np.inf
        cmin, cmax = np.inf, -np.inf
        for f in range(6):
            for k in range(4):
                p, c, n = _FACES[f, (k + 3) % 4], _FACES[f, k], _FACES[f, (k + 1) % 4]
                u0, u1, u2 = P[p, 0] - P[c, 0], P[p, 1] - P[c, 1], P[p, 2] - P[c, 2]
                v0, v1, v2 = P[n, 0] - P[c, 0], P[n, 1] - P[c, 1], P[n, 2] - P[c, 2]
                cs = (u0 * v0 + u1 * v1 + u2 * v2) / np.sqrt(
                    (u0 * u0 + u1 * u1 + u2 * u2) * (v0 * v0 + v1 * v1 + v2 * v2)
                )
                cmax = max(cmax, cs)  # arccos is monotone: only the extreme cosines need it
                cmin = min(cmin, cs)
        out[e, 5] = np.degrees(np.arccos(min(1.0, cmax)))
        out[e, 6] = np.degrees(np.arccos(max(-1.0, cmin)))
    return out


@numba.njit(cache=True)
def _bernstein_element_nb(Pe, f, g):
    """(min of the 27 Bernstein coefficients, min corner det J) of one hex Pe (8, 3); f, g: (3,3,3) scratch."""
    T = LAGRANGE_TO_BERNSTEIN
    for q in range(27):
        f[q // 9, (q // 3) % 3, q % 3] = _detj_nb(Pe, DN_HALF[q])
    # apply T along u, then v, then w (ping-pong between f and g)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                g[i, j, k] = T[i, 0] * f[0, j, k] + T[i, 1] * f[1, j, k] + T[i, 2] * f[2, j, k]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                f[i, j, k] = T[j, 0] * g[i, 0, k] + T[j, 1] * g[i, 1, k] + T[j, 2] * g[i, 2, k]
    cmin = np.inf
    for i in range(3):
        for j in range(3):
            for k in range(3):
                cmin = min(cmin, T[k, 0] * f[i, j, 0] + T[k, 1] * f[i, j, 1] + T[k, 2] * f[i, j, 2])
    corner = np.inf
    for i in (0, 2):
        for j in (0, 2):
            for k in (0, 2):
                corner = min(corner, f[i, j, k])  # T keeps endpoint values
    return cmin, corner


@numba.njit(cache=True)
def bernstein_bounds_nb(P):
    """For hexes P (M, 8, 3): (min of the 27 Bernstein coefficients of det J, min corner det J) -> two (M,)."""
    M = P.shape[0]
    min_coef = np.empty(M)
    min_corner = np.empty(M)
    f = np.empty((3, 3, 3))
    g = np.empty((3, 3, 3))
    for m in range(M):
        min_coef[m], min_corner[m] = _bernstein_element_nb(P[m], f, g)
    return min_coef, min_corner


@numba.njit(cache=True)
def bernstein_bounds_mesh_nb(X, conn):
    """bernstein_bounds_nb for all elements of one mesh X (n_nodes, 3), conn (E, 8), without gathering X[conn]."""
    E = conn.shape[0]
    min_coef = np.empty(E)
    min_corner = np.empty(E)
    f = np.empty((3, 3, 3))
    g = np.empty((3, 3, 3))
    Pe = np.empty((8, 3))
    for e in range(E):
        for k in range(8):
            for d in range(3):
                Pe[k, d] = X[conn[e, k], d]
        min_coef[e], min_corner[e] = _bernstein_element_nb(Pe, f, g)
    return min_coef, min_corner


@numba.njit(cache=True)
def scaled_jacobian_batch_nb(Xb, conn):
    """min_scaled_jacobian_nb for a batch Xb (B, n_nodes, 3) -> (B, E)."""
    out = np.empty((Xb.shape[0], conn.shape[0]))
    for b in range(Xb.shape[0]):
        out[b] = min_scaled_jacobian_nb(Xb[b], conn)
    return out


@numba.njit(cache=True)
def full_metrics_batch_nb(Xb, conn):
    """full_metrics_nb for a batch Xb (B, n_nodes, 3) -> (B, E, 7)."""
    out = np.empty((Xb.shape[0], conn.shape[0], 7))
    for b in range(Xb.shape[0]):
        out[b] = full_metrics_nb(Xb[b], conn)
    return out


_G = float(GAUSS_1D[0])  # Gauss abscissa 0.5 - 0.5 / sqrt(3) on [0, 1]; the other is 1 - _G

# The 12 edges as parametric derivatives: the u-edges (node p -> q along u) at (v, w) = (0,0), (1,0), (0,1), (1,1),
# the v-edges at (u, w) and the w-edges at (u, v) in the same order.  dX/du at (u, v, w) is the bilinear blend of
# the four u-edges; the principal axes of the centre Jacobian are their sums.
_PARAM_EDGES = np.array(
    [[0, 1], [3, 2], [4, 5], [7, 6], [0, 3], [1, 2], [4, 7], [5, 6], [0, 4], [1, 5], [3, 7], [2, 6]], dtype=np.int64
)


def _corner_edge_table() -> tuple[np.ndarray, np.ndarray]:
    """For corner i and its neighbours (a, b, c) of ``CORNER_NEIGHBOURS``: which parametric edge P_a - P_i is and
    its sign (+1 if the edge runs i -> a).  Negating is exact, so the corner's determinant, lengths and dot
    products from signed edges are bit-identical to those of P_a - P_i."""
    edge, sign = np.empty((8, 3), np.int64), np.empty((8, 3))
    for i in range(8):
        for j, a in enumerate(CORNER_NEIGHBOURS[i]):
            k = next(k for k, (p, q) in enumerate(_PARAM_EDGES) if {p, q} == {i, a})
            edge[i, j], sign[i, j] = k, (1.0 if _PARAM_EDGES[k, 0] == i else -1.0)
    return edge, sign


_CORNER_EDGE, _CORNER_SIGN = _corner_edge_table()
#: models per vector lane group of ``model_quality_lanes_nb``: batches are padded to a multiple (AVX-512: 8 doubles)
LANES = 8


@numba.njit(cache=True, boundscheck=False, error_model="numpy")
def model_quality_lanes_nb(XT, conn, part, n_parts, warn_sj, cos_warn_lo, cos_warn_hi, cos_160):
    """Check + Table 3 of a batch in one pass, vectorised across the models: XT (n_nodes, 3, B) mm (the batch
    transposed, so that one node coordinate of all B models is contiguous), conn (E, 8), part (E,) codes
    0..n_parts-1 -> (counts (n_parts, 4, B) int64, minima (n_parts, 3, B) float64).

    counts: errors (scaled J <= 0), warnings (not an error and scaled J < warn_sj or a face angle below the
    lower or above the upper warning angle), edge ratio > 10, max face angle > 160 deg; minima: scaled J,
    nodal and Gauss Jacobian ratio.  Face angles are compared as cosines (arccos is decreasing: an angle
    below 10 deg is a cosine above cos 10 deg), squared so that no square root is taken: d / sqrt(la lb) > c
    with d > 0 is d^2 > c^2 la lb.  The edge ratio likewise: sqrt(lmax / lmin) > 10 is lmax > 100 lmin.

    Every loop over the models is innermost and free of calls and branches, so LLVM turns it into vector
    instructions (error_model="numpy": no zero-division checks); element by element, the scaled J and the
    nodal ratio use the operands and order of ``full_metrics_nb``'s corner loop (bit-identical), the Gauss
    ratio the bilinear blends of the 12 edge vectors (the same trilinear map, round-off ~1e-15).  Memory:
    per-model scratch rows of B doubles; the element loop is the outer loop.
    """
    B = XT.shape[2]
    E = conn.shape[0]
    counts = np.zeros((n_parts, 4, B), dtype=np.int64)
    minima = np.full((n_parts, 3, B), np.inf)
    # the element's 12 parametric edge vectors (x, y, z) and their squared lengths, mm and mm^2: one array, so
    # that the loop forming them writes one array (one run-time alias check against the batch, not twelve)
    ed = np.empty((12, 4, B))
    gx = np.empty((3, 4, 3, B))  # dX/du, dX/dv, dX/dw at the four Gauss (v, w), (u, w), (u, v) pairs
    sj, amin, amax, gmin, gmax = np.empty(B), np.empty(B), np.empty(B), np.empty(B), np.empty(B)
    degenerate, lo, hi = np.empty(B, np.bool_), np.empty(B, np.bool_), np.empty(B, np.bool_)
    over160, long_edge = np.empty(B, np.bool_), np.empty(B, np.bool_)
    lo2, hi2, c1602 = cos_warn_lo * cos_warn_lo, cos_warn_hi * cos_warn_hi, cos_160 * cos_160
    for e in range(E):
        # each edge straight from the batch rows of its two nodes (30 % faster than copying the element's 8
        # nodes to a scratch array first)
        for k in range(12):
            ni, nj = conn[e, _PARAM_EDGES[k, 0]], conn[e, _PARAM_EDGES[k, 1]]
            a0, a1, a2, b0, b1, b2 = XT[ni, 0], XT[ni, 1], XT[ni, 2], XT[nj, 0], XT[nj, 1], XT[nj, 2]
            out = ed[k]
            for b in range(B):
                x = b0[b] - a0[b]
                y = b1[b] - a1[b]
                z = b2[b] - a2[b]
                out[0, b], out[1, b], out[2, b] = x, y, z
                out[3, b] = x * x + y * y + z * z
        for b in range(B):
            sj[b], amin[b], amax[b] = VERDICT_DBL_MAX, np.inf, -np.inf
            degenerate[b], lo[b], hi[b], over160[b] = False, False, False, False
        for i in range(8):
            ka, kb, kc = _CORNER_EDGE[i, 0], _CORNER_EDGE[i, 1], _CORNER_EDGE[i, 2]
            sa, sb, sc = _CORNER_SIGN[i, 0], _CORNER_SIGN[i, 1], _CORNER_SIGN[i, 2]
            sabc, sab, sbc, sca = sa * sb * sc, sa * sb, sb * sc, sc * sa
            for b in range(B):
                a0, a1, a2 = ed[ka, 0, b], ed[ka, 1, b], ed[ka, 2, b]
                b0, b1, b2 = ed[kb, 0, b], ed[kb, 1, b], ed[kb, 2, b]
                c0, c1, c2 = ed[kc, 0, b], ed[kc, 1, b], ed[kc, 2, b]
                la, lb, lc = ed[ka, 3, b], ed[kb, 3, b], ed[kc, 3, b]
                al = sabc * _det3_nb(a0, a1, a2, b0, b1, b2, c0, c1, c2)
                amin[b] = al if al < amin[b] else amin[b]
                amax[b] = al if al > amax[b] else amax[b]
                degenerate[b] |= (la <= VERDICT_DBL_MIN) | (lb <= VERDICT_DBL_MIN) | (lc <= VERDICT_DBL_MIN)
                s = al / np.sqrt(la * lb * lc)
                sj[b] = s if s < sj[b] else sj[b]
                # the corner's three face angles: every pair of its edges spans one of its three faces
                dab = sab * (a0 * b0 + a1 * b1 + a2 * b2)
                dbc = sbc * (b0 * c0 + b1 * c1 + b2 * c2)
                dca = sca * (c0 * a0 + c1 * a1 + c2 * a2)
                qab, qbc, qca = dab * dab, dbc * dbc, dca * dca
                pab, pbc, pca = la * lb, lb * lc, lc * la
                lo[b] |= (
                    ((dab > 0) & (qab > lo2 * pab)) | ((dbc > 0) & (qbc > lo2 * pbc)) | ((dca > 0) & (qca > lo2 * pca))
                )
                hi[b] |= (
                    ((dab < 0) & (qab > hi2 * pab)) | ((dbc < 0) & (qbc > hi2 * pbc)) | ((dca < 0) & (qca > hi2 * pca))
                )
                over160[b] |= (
                    ((dab < 0) & (qab > c1602 * pab))
                    | ((dbc < 0) & (qbc > c1602 * pbc))
                    | ((dca < 0) & (qca > c1602 * pca))
                )
        for direction in range(3):
            k0 = 4 * direction
            for q in range(4):
                s, t = (_G if q % 2 == 0 else 1.0 - _G), (_G if q < 2 else 1.0 - _G)
                f0, f1, f2, f3 = (1 - s) * (1 - t), s * (1 - t), (1 - s) * t, s * t
                for d in range(3):
                    for b in range(B):
                        gx[direction, q, d, b] = (
                            f0 * ed[k0, d, b] + f1 * ed[k0 + 1, d, b] + f2 * ed[k0 + 2, d, b] + f3 * ed[k0 + 3, d, b]
                        )
        for b in range(B):
            gmin[b], gmax[b] = np.inf, -np.inf
        for iu in range(2):
            for iv in range(2):
                for iw in range(2):
                    qu, qv, qw = iv + 2 * iw, iu + 2 * iw, iu + 2 * iv
                    for b in range(B):
                        g = _det3_nb(
                            gx[0, qu, 0, b], gx[0, qu, 1, b], gx[0, qu, 2, b],
                            gx[1, qv, 0, b], gx[1, qv, 1, b], gx[1, qv, 2, b],
                            gx[2, qw, 0, b], gx[2, qw, 1, b], gx[2, qw, 2, b],
                        )  # fmt: skip
                        gmin[b] = g if g < gmin[b] else gmin[b]
                        gmax[b] = g if g > gmax[b] else gmax[b]
        for b in range(B):
            # principal axes: the four parallel edges summed in _centre_sj_nb's order
            x10 = ((ed[0, 0, b] + ed[1, 0, b]) + ed[2, 0, b]) + ed[3, 0, b]
            x11 = ((ed[0, 1, b] + ed[1, 1, b]) + ed[2, 1, b]) + ed[3, 1, b]
            x12 = ((ed[0, 2, b] + ed[1, 2, b]) + ed[2, 2, b]) + ed[3, 2, b]
            x20 = ((ed[4, 0, b] + ed[5, 0, b]) + ed[6, 0, b]) + ed[7, 0, b]
            x21 = ((ed[4, 1, b] + ed[5, 1, b]) + ed[6, 1, b]) + ed[7, 1, b]
            x22 = ((ed[4, 2, b] + ed[5, 2, b]) + ed[6, 2, b]) + ed[7, 2, b]
            x30 = ((ed[8, 0, b] + ed[9, 0, b]) + ed[11, 0, b]) + ed[10, 0, b]
            x31 = ((ed[8, 1, b] + ed[9, 1, b]) + ed[11, 1, b]) + ed[10, 1, b]
            x32 = ((ed[8, 2, b] + ed[9, 2, b]) + ed[11, 2, b]) + ed[10, 2, b]
            l1 = x10 * x10 + x11 * x11 + x12 * x12
            l2 = x20 * x20 + x21 * x21 + x22 * x22
            l3 = x30 * x30 + x31 * x31 + x32 * x32
            centre = _det3_nb(x10, x11, x12, x20, x21, x22, x30, x31, x32) / np.sqrt(l1 * l2 * l3)
            bad = degenerate[b] | (l1 <= VERDICT_DBL_MIN) | (l2 <= VERDICT_DBL_MIN) | (l3 <= VERDICT_DBL_MIN)
            least = sj[b] if sj[b] < centre else centre
            sj[b] = VERDICT_DBL_MAX if bad else least
        # separate short loops: one loop writing many arrays needs more run-time alias checks than LLVM makes,
        # and stays scalar
        for b in range(B):
            amin[b] = -VERDICT_DBL_MAX if amax[b] <= VERDICT_DBL_MIN else amin[b] / amax[b]
        for b in range(B):
            gmin[b] = -VERDICT_DBL_MAX if gmax[b] <= VERDICT_DBL_MIN else gmin[b] / gmax[b]
        for b in range(B):
            lmin, lmax = ed[0, 3, b], ed[0, 3, b]
            for k in range(1, 12):
                lmin = ed[k, 3, b] if ed[k, 3, b] < lmin else lmin
                lmax = ed[k, 3, b] if ed[k, 3, b] > lmax else lmax
            long_edge[b] = lmax > 100.0 * lmin
        p = part[e]
        for b in range(B):
            error = sj[b] <= 0
            counts[p, 0, b] += error
            counts[p, 1, b] += ~error & ((sj[b] < warn_sj) | lo[b] | hi[b])
        for b in range(B):
            counts[p, 2, b] += long_edge[b]
        for b in range(B):
            counts[p, 3, b] += over160[b]
        for b in range(B):
            minima[p, 0, b] = sj[b] if sj[b] < minima[p, 0, b] else minima[p, 0, b]
        for b in range(B):
            minima[p, 1, b] = amin[b] if amin[b] < minima[p, 1, b] else minima[p, 1, b]
        for b in range(B):
            minima[p, 2, b] = gmin[b] if gmin[b] < minima[p, 2, b] else minima[p, 2, b]
    return counts, minima


@numba.njit(cache=True)
def transpose_into_lanes_nb(x, xt):
    """xt[i, d, b] = x[min(b, B - 1), i, d] in blocks of 256 nodes (the block's rows of every model stay in the
    cache while they are written): 1.7x numpy's transposing copy."""
    n_models, n_nodes = x.shape[0], xt.shape[0]
    for i0 in range(0, n_nodes, 256):
        i1 = min(n_nodes, i0 + 256)
        for b in range(xt.shape[2]):
            src = min(b, n_models - 1)
            for i in range(i0, i1):
                xt[i, 0, b] = x[src, i, 0]
                xt[i, 1, b] = x[src, i, 1]
                xt[i, 2, b] = x[src, i, 2]
