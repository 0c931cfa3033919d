"""The seed's Table 3 of mesh quality: every per-element metric of a mesh (``hex_quality_metrics``), their
summary per part (``table3_summary``), and the shard pass's per-model check and Table 3 columns from one
kernel pass over a batch (``model_quality``, ``table3_per_model``).

Errors are hexes with scaled Jacobian <= 0 (or without a Bernstein certificate, where it is computed): Abaqus'
ErrElemVolSmallNegZero.  Warnings are our proxy for Abaqus' WarnElemDistorted, whose limits are unpublished:
not an error and a scaled Jacobian below 0.2 or a face angle outside [10, 160] deg.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from spinecohort.mesh.quality.certificate import certify_valid
from spinecohort.mesh.quality.element import check_mesh
from spinecohort.mesh.quality.kernels import (
    LANES,
    full_metrics_batch_nb,
    model_quality_lanes_nb,
    transpose_into_lanes_nb,
)

if TYPE_CHECKING:  # a DataFrame only where a caller asks for one: the kernels return columns
    import pandas as pd


def hex_quality_metrics(points: np.ndarray, hexes: np.ndarray, certify: bool = True) -> dict[str, np.ndarray]:
    """All per-element metrics -> dict of (..., E) arrays (keys as in ``table3_summary``).

    Uses the numba full-metrics kernel; ``certificate`` (+1/-1) is the exact Bernstein check (if certify).
    """
    points, hexes = check_mesh(points, hexes)
    batch = points if points.ndim == 3 else points[None]
    out = full_metrics_batch_nb(np.ascontiguousarray(batch), hexes)
    names = (
        "scaled_jacobian",
        "jacobian",
        "nodal_jacobian_ratio",
        "gauss_jacobian_ratio",
        "edge_ratio",
        "min_face_angle_deg",
        "max_face_angle_deg",
    )
    metrics = {k: out[..., i] for i, k in enumerate(names)}
    if certify:
        metrics["certificate"] = certify_valid(batch, hexes)
    if points.ndim == 2:
        metrics = {k: v[0] for k, v in metrics.items()}
    return metrics


WARNING_MIN_SCALED_JACOBIAN = 0.2
WARNING_FACE_ANGLE_DEG = (10.0, 160.0)


def table3_summary(metrics: dict[str, np.ndarray], part_of_element: np.ndarray) -> pd.DataFrame:
    """Per-part rows with the seed's Table 3 columns, plus an 'all' row.

    metrics: from ``hex_quality_metrics``, arrays (E,) or (B, E) (pooled over samples: % of element instances).
    part_of_element: (E,) part label per element, e.g. "vertebra", "AF", "NP", "CEP".
    Columns:
      pct_errors      invalid: scaled Jacobian <= 0 or Bernstein certificate -1 (Abaqus ErrElemVolSmallNegZero).
      pct_warnings    not an error and (scaled Jacobian < 0.2 or a face angle outside [10, 160] deg); our proxy for
                      Abaqus WarnElemDistorted, whose limits are unpublished.
      nodal_jacobian_ratio_min/_p5, gauss_jacobian_ratio_min/_p5   corner and 2x2x2 Gauss min/max det J.
      pct_edge_ratio_gt_10, pct_max_face_angle_gt_160.
    """
    part = np.asarray(part_of_element)
    sj = np.asarray(metrics["scaled_jacobian"])
    if part.ndim != 1 or part.shape[0] != sj.shape[-1]:
        raise ValueError(f"part_of_element must have shape ({sj.shape[-1]},), got {part.shape}")
    missing = {
        "scaled_jacobian",
        "nodal_jacobian_ratio",
        "gauss_jacobian_ratio",
        "edge_ratio",
        "min_face_angle_deg",
        "max_face_angle_deg",
    } - set(metrics)
    if missing:
        raise ValueError(f"metrics lack {sorted(missing)}")
    m = {k: np.asarray(v).reshape(-1, sj.shape[-1]) for k, v in metrics.items()}
    error = m["scaled_jacobian"] <= 0
    if "certificate" in m:
        error |= m["certificate"] < 0
    warning = ~error & (
        (m["scaled_jacobian"] < WARNING_MIN_SCALED_JACOBIAN)
        | (m["min_face_angle_deg"] < WARNING_FACE_ANGLE_DEG[0])
        | (m["max_face_angle_deg"] > WARNING_FACE_ANGLE_DEG[1])
    )
    rows = []
    labels = list(dict.fromkeys(part.tolist())) + ["all"]
    for label in labels:
        sel = np.ones(len(part), bool) if label == "all" else part == label
        n = sel.sum() * m["scaled_jacobian"].shape[0]
        row = {
            "part": label,
            "n_elements": int(sel.sum()),
            "n_element_instances": int(n),
            "pct_errors": 100.0 * error[:, sel].mean(),
            "pct_warnings": 100.0 * warning[:, sel].mean(),
        }
        for k in ("nodal_jacobian_ratio", "gauss_jacobian_ratio"):
            v = m[k][:, sel]
            row[f"{k}_min"] = float(v.min())
            row[f"{k}_p5"] = float(np.percentile(v, 5))
        row["pct_edge_ratio_gt_10"] = 100.0 * (m["edge_ratio"][:, sel] > 10).mean()
        row["pct_max_face_angle_gt_160"] = 100.0 * (m["max_face_angle_deg"][:, sel] > 160).mean()
        rows.append(row)
    import pandas as pd

    return pd.DataFrame(rows)


def _lanes_of(x: np.ndarray, n_nodes: int) -> np.ndarray:
    """The first n_nodes rows of the batch x (B, N, 3) as ``model_quality_lanes_nb`` reads them: (n_nodes, 3, B')
    float64, B' = B rounded up to whole ``LANES`` (padded with copies of the last model)."""
    xt = np.empty((n_nodes, 3, -(-x.shape[0] // LANES) * LANES))
    if x.shape[0]:
        transpose_into_lanes_nb(x, xt)
    return xt


def part_codes(part_of_element: np.ndarray) -> tuple[np.ndarray, list, np.ndarray, np.ndarray]:
    """The part labels of the hexes as ``model_quality`` needs them: (code (E,) int64: index of each hex's
    label in order of first appearance, labels in that order, rank: sorted-label index -> that index,
    hexes per label (float64)).  Computed once per shard job (``model_quality(..., codes=...)``)."""
    part = np.asarray(part_of_element)
    uniq, first, inverse = np.unique(part, return_index=True, return_inverse=True)  # uniq sorted
    appearance = np.argsort(first, kind="stable")  # sorted-label indices in order of first appearance
    rank = np.empty(len(uniq), dtype=np.int64)
    rank[appearance] = np.arange(len(uniq))
    code = rank[inverse.ravel()]  # per element: its label's index in order of first appearance
    labels = uniq[appearance].tolist()
    n_el = np.bincount(code, minlength=len(labels)).astype(np.float64)
    return code.astype(np.int64), labels, rank, n_el


def model_quality(
    points: np.ndarray, hexes: np.ndarray, part_of_element: np.ndarray, codes: tuple | None = None
) -> dict[str, np.ndarray]:
    """The shard pass's per-model quality in one kernel pass (``model_quality_lanes_nb``): the check (scaled Jacobian
    per model and tissue) and the seed's Table 3 columns, from one evaluation of each hex's corner Jacobians.

    points (B, n_nodes, 3) mm (any float dtype, any layout: the kernel reads the node rows of ``hexes``);
    part_of_element (E,) labels (codes: their ``part_codes``, if already computed).  Returns (B,) arrays:
    ``min_sj`` and ``invalid`` (hexes with scaled Jacobian <= 0) over all hexes, ``min_sj_<part>`` per part
    (parts in sorted order), and the ``table3_per_model`` columns ``<metric>_<part>`` (parts in order of
    first appearance).
    """
    conn = np.ascontiguousarray(hexes, dtype=np.int64)
    if np.shape(part_of_element) != (len(conn),):
        raise ValueError(f"part_of_element must have shape ({len(conn)},), got {np.shape(part_of_element)}")
    code, labels, rank, n_el = part_codes(part_of_element) if codes is None else codes
    x = np.asarray(points)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"points must have shape (B, n_nodes, 3), got {x.shape}")
    if conn.size and (conn.min() < 0 or conn.max() >= x.shape[1]):  # the kernel does not bounds-check
        raise ValueError(f"hexes reference nodes outside 0..{x.shape[1] - 1}")
    lo_deg, hi_deg = WARNING_FACE_ANGLE_DEG
    counts, minima = model_quality_lanes_nb(
        _lanes_of(x, int(conn.max()) + 1 if conn.size else 0),
        conn,
        code,
        len(labels),
        WARNING_MIN_SCALED_JACOBIAN,
        np.cos(np.radians(lo_deg)),
        np.cos(np.radians(hi_deg)),
        np.cos(np.radians(160.0)),
    )
    counts, minima = counts[:, :, : len(x)].transpose(2, 0, 1), minima[:, :, : len(x)].transpose(2, 0, 1)
    out = {"min_sj": minima[:, :, 0].min(axis=1), "invalid": counts[:, :, 0].sum(axis=1)}
    for j in rank:  # sorted label order
        out[f"min_sj_{labels[j]}"] = minima[:, j, 0]
    for j, label in enumerate(labels):
        # 100 * (count / n): the value of 100 * mean(boolean mask) in table3_summary, bit for bit
        out[f"pct_errors_{label}"] = 100.0 * (counts[:, j, 0] / n_el[j])
        out[f"pct_warnings_{label}"] = 100.0 * (counts[:, j, 1] / n_el[j])
        out[f"nodal_jacobian_ratio_min_{label}"] = minima[:, j, 1]
        out[f"gauss_jacobian_ratio_min_{label}"] = minima[:, j, 2]
        out[f"pct_edge_ratio_gt_10_{label}"] = 100.0 * (counts[:, j, 2] / n_el[j])
        out[f"pct_max_face_angle_gt_160_{label}"] = 100.0 * (counts[:, j, 3] / n_el[j])
    return out


def table3_per_model(
    points: np.ndarray, hexes: np.ndarray, part_of_element: np.ndarray, chunk: int = 49
) -> pd.DataFrame:
    """The seed's Table 3 columns per model and part: one row per model of ``points`` (B, n_nodes, 3) mm.

    Columns ``<metric>_<part>`` for every part label (e.g. vertebra, AF, NP, CEP): ``pct_errors`` (scaled
    Jacobian <= 0), ``pct_warnings`` (as ``table3_summary``), ``nodal_jacobian_ratio_min``,
    ``gauss_jacobian_ratio_min``, ``pct_edge_ratio_gt_10``, ``pct_max_face_angle_gt_160``.  One
    ``model_quality`` pass per ``chunk`` models (float64); memory stays O(chunk x parts).
    """
    cols: dict[str, list[np.ndarray]] = {}
    for i in range(0, len(points), chunk):
        for k, v in model_quality(points[i : i + chunk], hexes, part_of_element).items():
            if k.startswith(("pct_", "nodal_", "gauss_")):
                cols.setdefault(k, []).append(v)
    import pandas as pd

    return pd.DataFrame({k: np.concatenate(v) for k, v in cols.items()})
