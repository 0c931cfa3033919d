"""Disc contact: keep every disc of a sampled model open, so that no model of the grid is collapsed.

A linear SSM extrapolated to several modes at ±3 SD at once can bring a vertebra's inferior endplate
*through* the endplate below it (on the default cohort: L5 into the sacral plate in 2 % of the 7^5 grid,
by up to 3 mm at the posterior rim).  Such a triangulated model interpenetrates, and no hexahedral disc
can fill a negative gap: local untangling, which keeps the endplates where they are, cannot repair it.

The correction here is the smallest rigid one that keeps the spinopelvic *angles*: for every disc whose
gap (signed distance of the upper endplate's nodes above the plane of the lower endplate, measured on the
hex model, since the FE model is what must stay valid) falls below
``min_height_mm``, everything cranial to that disc is translated along the lower endplate's normal until
the smallest gap equals ``min_height_mm`` — a distraction of the segment.  Endplate orientations, and so
PI, PT, SS, LL, the Cobb angle and the segmental angles, are unchanged; positions cranial to the disc
(SVA, T1 offsets) move by the distraction, at most a few millimetres; the disc heights of that disc grow
by it.  Triangulated and hexahedral models get the same translation (hex disc nodes the interpolation
between their two endplates with the weights that placed them in the mean), so the two stay in
correspondence, and the distraction of every model is recorded.

Disc ``j`` (``landmarks.DISCS[j]``) lies between ``LEVELS[j]`` and the level below, so level ``i`` moves by
the sum of the distractions of discs ``i ... 16``; the sacrum, pelvis and femoral heads never move.
Millimetres throughout.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np

from spinecohort.cohort.landmarks import DISCS, LEVELS, Landmarks
from spinecohort.mesh.template import HexTemplate, disc_runs


def _ragged(sets: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(concatenated indices int64, start offsets (len + 1,)) of a list of index arrays."""
    starts = np.zeros(len(sets) + 1, dtype=np.int64)
    starts[1:] = np.cumsum([len(v) for v in sets])
    flat = np.concatenate([np.asarray(v, dtype=np.int64).ravel() for v in sets]) if sets else np.zeros(0, np.int64)
    return flat, starts


@numba.njit(cache=True)
def _set_mean_nb(points, b, index, start, stop):
    """Mean of points[b, index[start:stop]] (float64), summed in index order as numpy's mean over that axis."""
    s0, s1, s2 = 0.0, 0.0, 0.0
    for i in range(start, stop):
        n = index[i]
        s0 += points[b, n, 0]
        s1 += points[b, n, 1]
        s2 += points[b, n, 2]
    k = stop - start
    return s0 / k, s1 / k, s2 / k


@numba.njit(cache=True)
def _disc_moments_nb(points, lower, lower_at, upper, upper_at, centre, cov, towards):
    """Per model b and disc d: centre[b, d] = mean of the lower endplate's vertices, cov[b, d] = the sum of
    their outer products about it, towards[b, d] = mean of the upper endplate's vertices (float64).

    The arithmetic of the per-disc numpy fit (mean, einsum of the outer products, in vertex order), so
    the planes are the same to the bit (tested), in one pass instead of 17 x 6 numpy calls per batch."""
    for b in range(points.shape[0]):
        for d in range(len(lower_at) - 1):
            c0, c1, c2 = _set_mean_nb(points, b, lower, lower_at[d], lower_at[d + 1])
            centre[b, d, 0], centre[b, d, 1], centre[b, d, 2] = c0, c1, c2
            xx, xy, xz, yy, yz, zz = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for i in range(lower_at[d], lower_at[d + 1]):
                n = lower[i]
                x = points[b, n, 0] - c0
                y = points[b, n, 1] - c1
                z = points[b, n, 2] - c2
                xx += x * x
                xy += x * y
                xz += x * z
                yy += y * y
                yz += y * z
                zz += z * z
            cov[b, d, 0, 0], cov[b, d, 0, 1], cov[b, d, 0, 2] = xx, xy, xz
            cov[b, d, 1, 0], cov[b, d, 1, 1], cov[b, d, 1, 2] = xy, yy, yz
            cov[b, d, 2, 0], cov[b, d, 2, 1], cov[b, d, 2, 2] = xz, yz, zz
            towards[b, d, 0], towards[b, d, 1], towards[b, d, 2] = _set_mean_nb(
                points, b, upper, upper_at[d], upper_at[d + 1]
            )


@numba.njit(cache=True)
def _smallest_gaps_nb(points, upper, upper_at, centre, normal, gaps):
    """gaps[b, d] = min over the upper endplate's vertices of (vertex - centre[b, d]) . normal[b, d]."""
    for b in range(points.shape[0]):
        for d in range(len(upper_at) - 1):
            g = np.inf
            for i in range(upper_at[d], upper_at[d + 1]):
                n = upper[i]
                v = (
                    (points[b, n, 0] - centre[b, d, 0]) * normal[b, d, 0]
                    + (points[b, n, 1] - centre[b, d, 1]) * normal[b, d, 1]
                    + (points[b, n, 2] - centre[b, d, 2]) * normal[b, d, 2]
                )
                g = min(g, v)
            gaps[b, d] = g


def disc_gaps(points: np.ndarray, upper: list[np.ndarray], lower: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Smallest gap (B, D) mm of every disc: vertices ``upper[j]`` (the upper vertebra's inferior endplate)
    over the least-squares plane of ``lower[j]`` (the lower endplate; its normal, the covariance's smallest
    eigenvector, oriented towards the upper endplate's centre), negative = interpenetration;
    and the lower endplates' normals (B, D, 3).  points (B, N, 3) mm.

    Two numba passes and one batched ``eigh`` for all discs (0.15 instead of 0.6 s per 2,401-model shard),
    the same numbers to the bit as numpy's fit disc by disc (tests/test_contact.py)."""
    pts = np.ascontiguousarray(points)
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    B, D = len(pts), len(upper)
    lo, lo_at = _ragged(lower)
    up, up_at = _ragged(upper)
    centre, towards = np.empty((B, D, 3)), np.empty((B, D, 3))
    cov = np.empty((B, D, 3, 3))
    _disc_moments_nb(pts, lo, lo_at, up, up_at, centre, cov, towards)
    _, vecs = np.linalg.eigh(cov)  # ascending: column 0 = plane normal
    normal = np.ascontiguousarray(vecs[..., 0])
    flip = np.einsum("bdc,bdc->bd", normal, towards - centre) < 0
    normal[flip] *= -1.0
    gaps = np.empty((B, D))
    _smallest_gaps_nb(pts, up, up_at, centre, normal, gaps)
    return gaps, normal


def level_offsets(gaps: np.ndarray, normals: np.ndarray, min_height_mm: float) -> np.ndarray:
    """Translation (B, 17, 3) mm of every level (T1..L5) that opens every disc to at least ``min_height_mm``."""
    distraction = np.maximum(min_height_mm - gaps, 0.0)[..., None] * normals  # (B, 17, 3) per disc
    # level i sits above discs i..16: suffix sum over the discs
    return np.cumsum(distraction[:, ::-1], axis=1)[:, ::-1]


@dataclass(frozen=True)
class ContactMap:
    """Where the gaps are measured and how the 17 level translations reach every node.

    Gaps are measured on the **hex** model (node sets ``EP_INF_<upper>`` over ``EP_SUP_<lower>``: the FE
    model is what must stay valid); the offsets move hex nodes and triangulated vertices alike.
    tri_level (N,) int: level index of every triangulated vertex (-1: sacrum, pelvis, femoral heads);
    hex (n_nodes, 17): a one for a vertebra's nodes, ``1 - s`` / ``s`` for hex disc nodes between two
    levels (``s`` from the mean), zeros for the sacrum side."""

    tri_level: np.ndarray
    hex: np.ndarray
    upper: list[np.ndarray]
    lower: list[np.ndarray]
    min_height_mm: float

    def gaps(self, hex_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """disc_gaps of hex models (B, n_nodes, 3) mm -> gaps (B, 17) mm, normals (B, 17, 3)."""
        return disc_gaps(hex_points, self.upper, self.lower)

    def level_offsets(self, hex_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gaps before (B, 17) mm, level offsets (B, 17, 3) mm) of hex models (B, n_nodes, 3)."""
        gaps, normals = self.gaps(hex_points)
        return gaps, level_offsets(gaps, normals, self.min_height_mm)

    def level_offsets_of_weights(
        self, mean: np.ndarray, fields: np.ndarray, weights: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``level_offsets`` of the linear models ``mean + fields . w`` (mean (n, 3), fields (m, n, 3) mm,
        weights (B, m) SD), sampling only the endplate nodes (no full model is formed)."""
        nodes = np.unique(np.concatenate(self.upper + self.lower))
        local = np.searchsorted(nodes, np.arange(len(mean)))  # valid at the kept nodes
        pts = mean[nodes] + np.tensordot(weights, fields[: weights.shape[1], nodes], axes=(1, 0))
        gaps, normals = disc_gaps(pts, [local[u] for u in self.upper], [local[lo] for lo in self.lower])
        return gaps, level_offsets(gaps, normals, self.min_height_mm)

    def hex_offsets(self, level_offsets_mm: np.ndarray) -> np.ndarray:
        """Hex node offsets (B, n_nodes, 3) mm."""
        return np.einsum("nl,blc->bnc", self.hex, level_offsets_mm)

    @cached_property
    def hex_sparse(self) -> tuple[np.ndarray, np.ndarray]:
        """``hex`` as (level (n_nodes, 2) int64, weight (n_nodes, 2) float64), its nonzeros in level order
        (level -1: none).  A node follows at most two levels (a disc node between its two endplates), so the
        offsets need two products per node instead of the 17 of the dense ``hex_offsets``."""
        nz = self.hex != 0
        if nz.sum(axis=1).max(initial=0) > 2:
            raise ValueError("contact map: a hex node follows more than two levels")
        order = np.argsort(~nz, axis=1, kind="stable")[:, :2]  # the nonzero columns first, in level order
        level = np.where(np.take_along_axis(nz, order, axis=1), order, -1)
        weight = np.where(level >= 0, np.take_along_axis(self.hex, order, axis=1), 0.0)
        return np.ascontiguousarray(level, dtype=np.int64), np.ascontiguousarray(weight, dtype=np.float64)

    def tri_offsets(self, level_offsets_mm: np.ndarray) -> np.ndarray:
        """Triangulated vertex offsets (B, N, 3) mm."""
        padded = np.concatenate([level_offsets_mm, np.zeros((len(level_offsets_mm), 1, 3))], axis=1)
        return padded[:, self.tri_level]  # index -1 -> the zero row

    def arrays(self) -> dict[str, np.ndarray]:
        """Flat arrays for an .npz (``from_arrays`` reads them back)."""
        out = {
            "contact_tri_level": self.tri_level.astype(np.int8),
            "contact_hex": self.hex.astype(np.float32),
            "contact_min_height_mm": np.array(self.min_height_mm),
        }
        for j in range(len(self.upper)):
            out[f"contact_upper_{j:02d}"] = self.upper[j]
            out[f"contact_lower_{j:02d}"] = self.lower[j]
        return out

    @classmethod
    def from_arrays(cls, z) -> ContactMap | None:
        if "contact_hex" not in z:
            return None
        nd = len(DISCS)
        return cls(
            np.asarray(z["contact_tri_level"], dtype=np.int64),
            np.asarray(z["contact_hex"], dtype=np.float64),
            [np.asarray(z[f"contact_upper_{j:02d}"]) for j in range(nd)],
            [np.asarray(z[f"contact_lower_{j:02d}"]) for j in range(nd)],
            float(z["contact_min_height_mm"]),
        )


def _level_of_part(landmarks: Landmarks) -> np.ndarray:
    """(N,) level index of every triangulated vertex (body_X / posterior_X), -1 for the rest."""
    index = {lv: i for i, lv in enumerate(LEVELS)}
    lut = np.array(
        [
            index.get(name.split("_", 1)[1], -1) if name.startswith(("body_", "posterior_")) else -1
            for name in landmarks.part_names
        ]
    )
    return lut[landmarks.part]


def contact_map(landmarks: Landmarks, template: HexTemplate, hex_mean: np.ndarray, min_height_mm: float) -> ContactMap:
    """The ContactMap of a triangulated topology and a morphed hex template (``hex_mean`` (n_nodes, 3) mm)."""
    if not min_height_mm >= 0:
        raise ValueError(f"min_height_mm must be >= 0, got {min_height_mm}")
    nl = len(LEVELS)
    tri_level = _level_of_part(landmarks)
    n_hex = template.n_hex_nodes
    layers = template.layers
    n2 = n_hex // len(layers)
    layer_w = np.zeros((len(layers), n2, nl))
    for L, layer in enumerate(layers):
        if layer["kind"] == "body":
            layer_w[L, :, LEVELS.index(layer["level"])] = 1.0
    mean_layers = np.asarray(hex_mean[:n_hex], dtype=np.float64).reshape(len(layers), n2, 3)
    for first, end in disc_runs(layers):  # as hex_ssm._interpolate_disc_fields: s from the mean
        lower, upper = mean_layers[first - 1], mean_layers[end]
        d = upper - lower
        for k in range(first, end):
            s = np.einsum("nc,nc->n", mean_layers[k] - lower, d) / np.einsum("nc,nc->n", d, d)
            layer_w[k] = (1 - s)[:, None] * layer_w[first - 1] + s[:, None] * layer_w[end]
    hexw = np.zeros((len(hex_mean), nl))
    hexw[:n_hex] = layer_w.reshape(n_hex, nl)
    sv_level = tri_level[template.surface_vertex]
    on = sv_level >= 0
    hexw[n_hex + np.flatnonzero(on), sv_level[on]] = 1.0
    ns = template.nsets
    upper = [np.asarray(ns[f"EP_INF_{u}"]) for u, _ in DISCS]
    lower = [np.asarray(ns[f"EP_SUP_{lo}"]) for _, lo in DISCS]
    return ContactMap(tri_level, hexw, upper, lower, float(min_height_mm))


@numba.njit(cache=True)
def _add_hex_offsets_nb(points, models, level, weight, off):
    """points[k] += the hex offsets of off[k] (17, 3) for k in models, in place (float64).

    The sum over a node's (at most two) levels in level order, from 0.0, then one addition to the point:
    the arithmetic of ``points[k] + einsum("nl,lc->nc", hex, off[k])`` (the dense sum's other terms are
    exact zeros), so the result is the same to the bit, without the (k, n, 3) temporaries."""
    for k in models:
        for n in range(points.shape[1]):
            for c in range(3):
                acc = 0.0
                for j in range(2):
                    lv = level[n, j]
                    if lv >= 0:
                        acc += weight[n, j] * off[k, lv, c]
                points[k, n, c] += acc


@numba.njit(cache=True)
def add_level_offsets_nb(points, models, tri_level, off):
    """points[k, i] += off[k, tri_level[i]] (0 where tri_level is -1) for k in models, in place (float64):
    the tri vertices' distraction (or that of any rows of them, with their levels)."""
    for k in models:
        for n in range(points.shape[1]):
            lv = tri_level[n]
            for c in range(3):
                points[k, n, c] += off[k, lv, c] if lv >= 0 else 0.0


def resolve_contact(tri: np.ndarray | None, hexp: np.ndarray, cmap: ContactMap) -> tuple[np.ndarray, np.ndarray]:
    """Open the collapsed discs of a batch **in place**: tri (B, N, 3) (or None), hex (B, n, 3) mm.

    Returns the gaps before (B, 17) mm and the level offsets applied (B, 17, 3) mm (zero where no disc
    was below ``cmap.min_height_mm``).  Only the models that need it are touched: float64 C-contiguous
    batches (the shard job's) in place by one numba pass per array (the dense einsum, its float64 copy
    and the fancy-indexed ``+=`` cost ~10 s of a 2,401-model shard with 350 distracted models), other
    dtypes by the dense offsets cast to their dtype."""
    gaps, off = cmap.level_offsets(hexp)
    moved = np.flatnonzero(np.abs(off).max(axis=(1, 2)) > 0)
    if len(moved):
        for pts, is_hex in ((hexp, True), (tri, False)):
            if pts is None:
                continue
            if pts.dtype == np.float64 and pts.flags.c_contiguous:
                if is_hex:
                    _add_hex_offsets_nb(pts, moved, *cmap.hex_sparse, off)
                else:
                    add_level_offsets_nb(pts, moved, np.ascontiguousarray(cmap.tri_level, dtype=np.int64), off)
            else:
                dense = cmap.hex_offsets(off[moved]) if is_hex else cmap.tri_offsets(off[moved])
                pts[moved] += dense.astype(pts.dtype)
    return gaps, off


def distraction_summary(gaps: np.ndarray, off: np.ndarray) -> dict[str, np.ndarray]:
    """Per model: smallest disc gap before (mm), the discs opened ("L5-S1;L4-L5" or ""), and the
    largest level offset (mm, the total distraction of T1)."""
    # disc j was opened iff level j moved more than level j + 1
    step = off - np.concatenate([off[:, 1:], np.zeros((len(off), 1, 3))], axis=1)
    opened = np.linalg.norm(step, axis=2) > 0
    names = np.array([f"{u}-{lo}" for u, lo in DISCS])
    return {
        "min_disc_gap_before_mm": gaps.min(axis=1),
        "discs_opened": np.array([";".join(names[row]) for row in opened], dtype=object),
        "distraction_mm": np.linalg.norm(off, axis=2).max(axis=1),
    }
