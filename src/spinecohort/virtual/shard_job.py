"""Per-shard logic of the virtual-cohort stage: sample, check and repair, measure, store (one shard = one job).

It sits above ``spinecohort.store`` (which imports nothing else of spinecohort) and calls down into ``ssm``,
``mesh``, ``measure`` and ``store``: the measurement runs on the float64 coordinates before the store
rounds them, so it belongs to the job, not to the store.

A shard is a contiguous model-ID range (``store.shard_range``).  ``process_shard`` makes one pass over it
in batches of whole store chunks: it samples the hexahedral SSM's volume nodes and the triangulated SSM's
landmark rows (float64 formula plus the disc-contact distraction), checks every hex of every model and
computes its Table 3 rows in one numba pass (``quality.model_quality``: each hex's corner Jacobians are
formed once for both), untangles the models with inverted hexes exactly as ``models.hex_points_checked``
does (``repair.untangle`` against the hex mean, one ``UntangleContext`` per job; only those models are
evaluated again), computes the spinopelvic parameters on those float64 coordinates, and hands the batch to
the store's ``ShardWriter``: the hex volume as float64, the triangulated models as their formula
(``LinearPoints``: the writer forms each store chunk straight in stored order, so the 81k-vertex models
never exist in float64); nothing is read back.  Memory is one batch (56 models x (11k hex volume nodes +
18k tri landmark rows) x 3 x 8 B ~ 39 MB of float64) and one store chunk, whatever the shard size.  Check
and repair happen *before* the store write, so the store only ever holds the coordinates the FE models use;
a model that cannot be repaired is kept as sampled and reported (``invalid_after > 0``).

``hex_landmarks`` builds a :class:`Landmarks` on the hex model's node numbering (hex nodes, then surface
nodes), so ``measure.measure`` runs unchanged on the hex coordinates (in the shard pass on its landmark
rows, ``Landmarks.measured``) and the tri-vs-hex difference of every parameter can be reported.  Millimetres
and degrees throughout.
"""

from __future__ import annotations

import os
import time
import warnings

import numba
import numpy as np
import pandas as pd
import zarr

from spinecohort.cohort.landmarks import DISCS, LEVELS, Landmarks
from spinecohort.measure.spinopelvic import measure_columns
from spinecohort.mesh.contact import add_level_offsets_nb, distraction_summary, resolve_contact
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.quality.table3 import model_quality, part_codes
from spinecohort.mesh.repair import RepairError, prepare_untangle, untangle
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM
from spinecohort.store.chunks import LinearPoints, linear_fields
from spinecohort.store.columns import QUALITY_SUMMARY, Columns, concat_columns
from spinecohort.store.grid import model_name, shard_range, weights_of
from spinecohort.store.writer import ShardWriter

#: models per batch: 8 store chunks of 7 models, and a whole number of the quality kernel's vector lanes
#: (``quality.LANES``), so no lane is padding
DEFAULT_CHUNK = 56


def _check_weights(weights: np.ndarray, n_available: int, what: str) -> np.ndarray:
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] < 1:
        raise ValueError(f"weights must be (models, modes) with at least one model, got shape {w.shape}")
    if w.shape[1] > n_available:
        raise ValueError(f"weights have {w.shape[1]} modes but the {what} has only {n_available}")
    if not np.all(np.isfinite(w)):
        raise ValueError("weights contain non-finite values")
    return w


def sample_points(
    ssm: SSM, hex_ssm: HexSSM, weights: np.ndarray, chunk: int = DEFAULT_CHUNK, return_contact: bool = False
):
    """(tri (S, N, 3), hex (S, n_nodes, 3)) float32 mm of ``SSM.sample`` / ``HexSSM.sample`` for weights (S, m),
    with the disc-contact distraction of ``hex_ssm.contact`` applied (``spinecohort.mesh.contact``).

    Computed in float64 batches of ``chunk`` models (one BLAS product each) and cast to float32, the
    store's dtype, so the float64 intermediate never holds the whole shard.  ``return_contact``: also
    return the disc gaps before (S, 17) mm and the level offsets applied (S, 17, 3) mm.
    """
    w = _check_weights(weights, min(ssm.n_modes, hex_ssm.fields.shape[0]), "SSM")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    m = w.shape[1]
    tri = np.empty((len(w), *ssm.mean.shape), np.float32)
    hexp = np.empty((len(w), *hex_ssm.mean.shape), np.float32)
    df_tri = ssm.deformation_fields(m).reshape(m, -1)
    df_hex = hex_ssm.fields[:m].reshape(m, -1)
    gaps = np.full((len(w), len(DISCS)), np.inf)
    offsets = np.zeros((len(w), len(DISCS), 3))
    for i in range(0, len(w), chunk):
        wb = w[i : i + chunk]
        t64 = (ssm.mean.ravel() + wb @ df_tri).reshape(len(wb), *ssm.mean.shape)
        h64 = (hex_ssm.mean.ravel() + wb @ df_hex).reshape(len(wb), *hex_ssm.mean.shape)
        if hex_ssm.contact is not None:
            gaps[i : i + chunk], offsets[i : i + chunk] = resolve_contact(t64, h64, hex_ssm.contact)
        tri[i : i + chunk] = t64
        hexp[i : i + chunk] = h64
    return (tri, hexp, gaps, offsets) if return_contact else (tri, hexp)


def shard_quality(
    hex_points: np.ndarray,
    template: HexTemplate,
    hex_ssm: HexSSM,
    weights: np.ndarray,
    model_ids: np.ndarray,
    repair: bool = True,
    log=None,
) -> tuple[Columns, Columns]:
    """Check every hex of every model, untangle the models with inverted hexes **in place**, and the seed's
    Table 3 rows: one ``quality.model_quality`` pass over the batch (the corner Jacobians of each hex are
    formed once for both), plus one more over the few repaired models.

    hex_points (S, n_nodes, 3) mm: the coordinates to check, as they will be stored (``process_shard``
    passes its float64 batch: the SSM formula plus the disc-contact distraction); ``weights`` (S, m) SD
    and ``model_ids`` name the models.  Repaired models (``repair.untangle`` against the hex mean) are
    written back into ``hex_points``.  Returns (check rows, Table 3 rows) as ``columns.Columns`` (ordered
    name -> (S,) array; ``pandas.DataFrame`` of either is the table), one row per model.  Check rows:
    ``min_sj_before/after``, ``invalid_before/after`` (hexes with sJ <= 0), ``nodes_moved``,
    ``max_displacement_mm``, ``repaired``, ``repair_error`` (empty or the RepairError message) and
    ``min_sj_<tissue>`` (after repair); Table 3 rows: ``table3_per_model``'s columns, after repair.
    repair=False only checks (then invalid_after == invalid_before).
    """
    w = _check_weights(weights, hex_ssm.fields.shape[0], "hex SSM")
    if hex_points.shape != (len(w), *hex_ssm.mean.shape):
        raise ValueError(f"hex_points must be {(len(w), *hex_ssm.mean.shape)}, got {hex_points.shape}")
    checked = _check_models(hex_points, _QualityInputs(template, hex_ssm), w, model_ids, repair, log)
    return _quality_columns(model_ids, *checked)


class _QualityInputs:
    """What every check of a shard shares: the template's hexes and parts, the hex mean (untangling's
    reference) and, built on the first model that needs it, the untangling context."""

    def __init__(self, template: HexTemplate, hex_ssm: HexSSM):
        self.n = template.n_hex_nodes
        self.hexes = np.ascontiguousarray(template.hexes, dtype=np.int64)
        self.part = template.part_of_hex()
        self.codes = part_codes(self.part)
        self.mean = np.ascontiguousarray(hex_ssm.mean[: self.n])
        self._ctx = None

    @property
    def ctx(self):
        if self._ctx is None:  # topology + reference quality, shared by every model
            self._ctx = prepare_untangle(self.hexes, self.mean)
        return self._ctx


def _check_models(hex_points, qi: _QualityInputs, w, model_ids, repair, log) -> tuple[dict, dict]:
    """``model_quality`` of hex_points (S, n_nodes, 3) mm, untangling the models with inverted hexes in place
    (and their quality again); returns (metrics, repairs): per-model arrays, no tables."""
    metrics = model_quality(hex_points, qi.hexes, qi.part, qi.codes)
    metrics["min_sj_before"], metrics["invalid_before"] = metrics["min_sj"].copy(), metrics["invalid"].copy()
    rep = {
        "nodes_moved": np.zeros(len(w), np.int64),
        "max_displacement_mm": np.zeros(len(w)),
        "repaired": np.zeros(len(w), bool),
        "repair_error": np.full(len(w), "", dtype=object),
    }
    bad = np.flatnonzero(metrics["invalid"])
    fixed_models = []
    n = qi.n
    for k in bad if repair else ():  # few models per shard (~2 % on the default grid); untangle is per mesh
        try:
            fixed, r = untangle(np.array(hex_points[k, :n], dtype=np.float64), qi.hexes, qi.mean, context=qi.ctx)
        except RepairError as exc:
            rep["repair_error"][k] = f"{model_name(int(model_ids[k]))}: {exc}"
            if log is not None:
                log.warning(
                    "%s (weights %s SD) cannot be repaired, stored as sampled with %d inverted hexes: %s",
                    model_name(int(model_ids[k])),
                    w[k].tolist(),
                    metrics["invalid"][k],
                    exc,
                )
            continue
        hex_points[k, :n] = fixed
        fixed_models.append(k)
        rep["nodes_moved"][k] = len(r.moved_nodes)
        rep["max_displacement_mm"][k] = r.max_displacement_mm
        rep["repaired"][k] = True
    if fixed_models:  # the repaired models' quality, evaluated again on their new coordinates
        again = model_quality(hex_points[fixed_models], qi.hexes, qi.part, qi.codes)
        for key, v in again.items():
            metrics[key][fixed_models] = v
    return metrics, rep


def _quality_columns(model_ids, metrics: dict, rep: dict) -> tuple[Columns, Columns]:
    """(check rows, Table 3 rows) of ``_check_models``' arrays (see :func:`shard_quality`): the summary
    columns of the sheet first (spelled once, ``columns.QUALITY_SUMMARY``), then the repair error and the
    per-tissue minima."""
    rows = {
        "model_id": np.asarray(model_ids, dtype=np.int64),
        "min_sj_before": metrics["min_sj_before"],
        "invalid_before": metrics["invalid_before"],
        **rep,
        "min_sj_after": metrics["min_sj"],
        "invalid_after": metrics["invalid"],
    }
    for key, v in metrics.items():
        if key.startswith("min_sj_") and key != "min_sj_before":
            rows[key] = v
    first = ["model_id", *QUALITY_SUMMARY, "repair_error"]
    check = {k: rows[k] for k in first} | {k: v for k, v in rows.items() if k not in first}
    skip = ("min_sj", "invalid", "min_sj_before", "invalid_before")
    table3 = {k: v for k, v in metrics.items() if k not in skip and k not in rows}
    return check, table3


def check_and_repair(
    hex_points: np.ndarray,
    template: HexTemplate,
    hex_ssm: HexSSM,
    weights: np.ndarray,
    model_ids: np.ndarray,
    repair: bool = True,
    log=None,
) -> Columns:
    """The check rows of :func:`shard_quality` (scaled Jacobian of every hex, untangling in place)."""
    return shard_quality(hex_points, template, hex_ssm, weights, model_ids, repair, log)[0]


def _param_diff(p_tri: Columns, p_hex: Columns) -> Columns:
    """Per numeric parameter: max and mean |tri - hex| over the models (NaN where a column is all NaN) and
    ``n_models``, how many models the mean is over (the cohort's mean pools the shards' means by it)."""
    num = [k for k, v in p_tri.items() if np.asarray(v).dtype.kind in "iuf"]  # not booleans, not strings
    d = np.abs(np.stack([p_tri[k] for k in num], axis=1) - np.stack([p_hex[k] for k in num], axis=1))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns (GAP without age) stay NaN
        largest = np.nanmax(np.where(np.isnan(d), -np.inf, d), axis=0)
        mean = np.nanmean(d, axis=0)
    return {
        "parameter": np.array(num, dtype=object),
        "max_abs_diff": np.where(np.isfinite(largest), largest, np.nan),
        "mean_abs_diff": mean,
        "n_models": np.count_nonzero(~np.isnan(d), axis=0),
    }


def _params_table(weights: np.ndarray, model_ids: np.ndarray, p_tri: Columns) -> Columns:
    w = np.asarray(weights, dtype=np.float64)
    head = {"model_id": np.array(model_name(np.asarray(model_ids)), dtype=object)}
    return head | {f"w{i + 1}": w[:, i] for i in range(w.shape[1])} | p_tri


@numba.njit(cache=True)
def _landmark_rows_nb(volume, volume_rows, tri, tri_rows, out):
    """out[k] = volume[k, volume_rows] then tri[k, tri_rows] for every model k (the hex model's landmark rows:
    its volume nodes, then the tri vertices its skin nodes are); 0.4 ms per 56 models, numpy's two fancy
    indexes and a concatenate 2.2 ms."""
    n = volume_rows.shape[0]
    for k in range(out.shape[0]):
        for i in range(n):
            for c in range(3):
                out[k, i, c] = volume[k, volume_rows[i], c]
        for i in range(tri_rows.shape[0]):
            for c in range(3):
                out[k, n + i, c] = tri[k, tri_rows[i], c]


def process_shard(
    ssm: SSM,
    hex_ssm: HexSSM,
    template: HexTemplate,
    weights: np.ndarray,
    model_ids: np.ndarray,
    tri_landmarks: Landmarks,
    hex_lm: Landmarks,
    writer=None,
    batch: int = DEFAULT_CHUNK,
    repair: bool = True,
    log=None,
    **measure_kw,
) -> tuple[Columns, Columns, Columns, dict]:
    """One pass over a shard, batch by batch, nothing decoded again: sample (float64 SSM formula + disc
    contact) -> check every hex and its Table 3 rows, repair inverted models -> spinopelvic parameters of the
    tri and the hex model -> ``writer.add`` (a :class:`~spinecohort.store.writer.ShardWriter`; None: no
    store write).  The parameters come from the float64 coordinates, i.e. from what the store holds before
    its 2^-10 mm rounding.

    ``batch`` models per step (rounded up to whole store chunks by the caller); ``measure_kw``: vertical,
    assumed_age, c7_proxy.  Returns (quality, params, tri-vs-hex tables as ``columns.Columns``, timing: wall ``<phase>_s``
    and CPU ``<phase>_cpu_s`` (of it kernel time ``<phase>_sys_s``) in s of the phases sample, quality (check +
    repair + Table 3), measure, write).
    """
    w = _check_weights(weights, min(ssm.n_modes, hex_ssm.fields.shape[0]), "SSM")
    ids = np.asarray(model_ids, dtype=np.int64)
    if len(ids) != len(w):
        raise ValueError(f"{len(w)} weights but {len(ids)} model IDs")
    m = w.shape[1]
    n_vol = template.n_hex_nodes
    if n_vol + len(template.surface_vertex) != len(hex_ssm.mean):
        raise ValueError(
            f"the template's {n_vol} + {len(template.surface_vertex)} nodes are not the hex SSM's {len(hex_ssm.mean)}"
        )
    # the hex volume and the tri landmark rows in float64 (the mean as a last mode of weight 1: one BLAS pass
    # writes mean + DF . b, the product's last FMA adding the mean); the whole tri models only as the store
    # holds them, chunk by chunk in the writer (LinearPoints: never a float64 tri batch, docs/explanation/performance.md).
    # The hex model is measured on its landmark rows: the volume ones from the hex volume, the surface ones
    # (femoral heads, symphysis) from their tri vertices
    hex_rows, hex_lm_rows = hex_lm.measured()
    surface_vertex = np.asarray(template.surface_vertex)
    vol_rows, skin_vertices = hex_rows[hex_rows < n_vol], surface_vertex[hex_rows[hex_rows >= n_vol] - n_vol]
    tri_rows, tri_lm_rows = tri_landmarks.measured(extra=skin_vertices)
    skin_rows = np.searchsorted(tri_rows, skin_vertices)
    df_rows = np.vstack([ssm.deformation_fields(m)[:, tri_rows].reshape(m, -1), ssm.mean[tri_rows].reshape(1, -1)])
    df_vol = np.vstack([hex_ssm.fields[:m, :n_vol].reshape(m, -1), hex_ssm.mean[:n_vol].reshape(1, -1)])
    tri_terms = linear_fields(ssm.mean, ssm.deformation_fields(m)) if writer is not None else None
    contact = hex_ssm.contact
    if contact is not None:
        tri_level = np.ascontiguousarray(contact.tri_level, dtype=np.int64)
        rows_level = tri_level[tri_rows]
    phases = ("sample", "quality", "measure", "write")
    # wall, CPU (user + system) and of it system (kernel) time per phase
    timing = {f"{k}{unit}": 0.0 for unit in ("_s", "_cpu_s", "_sys_s") for k in phases}

    def clock() -> tuple[float, float, float]:
        return time.perf_counter(), time.process_time(), os.times().system

    def tick(phase: str, start: tuple) -> tuple[float, float, float]:
        now = clock()
        for unit, t1, t0 in zip(("_s", "_cpu_s", "_sys_s"), now, start):
            timing[phase + unit] += t1 - t0
        return now

    qi = _QualityInputs(template, hex_ssm)
    quality, p_tri, p_hex = [], [], []
    hex_landmark_points = np.empty((min(batch, len(w)), len(hex_rows), 3))
    # float64 batch buffers reused batch after batch: fresh arrays per batch cost more in page faults than the
    # products that fill them
    r_buf = np.empty((min(batch, len(w)), len(tri_rows), 3))
    v_buf = np.empty((min(batch, len(w)), n_vol, 3))
    for i in range(0, len(w), batch):
        wb, ib = w[i : i + batch], ids[i : i + batch]
        at = clock()
        w1 = np.hstack([wb, np.ones((len(wb), 1))])
        r64, v64 = r_buf[: len(wb)], v_buf[: len(wb)]
        np.matmul(w1, df_rows, out=r64.reshape(len(wb), -1))
        np.matmul(w1, df_vol, out=v64.reshape(len(wb), -1))
        offsets = None
        if contact is not None:  # gaps and offsets come from the endplate (volume) nodes
            gaps, offsets = resolve_contact(None, v64, contact)
            moved = np.flatnonzero(np.abs(offsets).max(axis=(1, 2)) > 0)
            add_level_offsets_nb(r64, moved, rows_level, offsets)
        at = tick("sample", at)
        # check, repair and the seed's Table 3 columns in one pass, on the coordinates the store holds (the
        # hex skin is the tri surface, distracted or not: the store keeps it once, hex/surface_vertex)
        q, table3 = _quality_columns(ib, *_check_models(v64, qi, wb, ib, repair, log))
        if contact is not None:
            q |= distraction_summary(gaps, offsets)
        quality.append(q | table3)
        at = tick("quality", at)
        p_tri.append(measure_columns(r64, tri_lm_rows, **measure_kw))
        _landmark_rows_nb(v64, vol_rows, r64, skin_rows, hex_landmark_points[: len(wb)])
        p_hex.append(measure_columns(hex_landmark_points[: len(wb)], hex_lm_rows, **measure_kw))
        at = tick("measure", at)
        if writer is not None:
            tri = LinearPoints(tri_terms, wb, None if contact is None else tri_level, offsets)
            writer.add(tri, v64)
        tick("write", at)
    p_tri, p_hex = concat_columns(p_tri), concat_columns(p_hex)
    return concat_columns(quality), _params_table(w, ids, p_tri), _param_diff(p_tri, p_hex), timing


# ---------------------------------------------------------------------------------------- landmarks
def _nearest_layer_nodes(layer_nodes: np.ndarray, layer_points: np.ndarray, band_points: np.ndarray) -> np.ndarray:
    """The layer's nodes nearest to the band's points (each band point votes for one node), sorted."""
    from scipy.spatial import cKDTree

    return np.unique(layer_nodes[cKDTree(layer_points).query(band_points)[1]])


def hex_landmarks(
    template: HexTemplate, landmarks: Landmarks, mean_hex: np.ndarray | None = None, mean_tri: np.ndarray | None = None
) -> Landmarks:
    """Landmarks of the hex model (node numbering of ``template.nodes``) from the cohort's ``landmarks``.

    Endplates = node sets ``EP_SUP_<lvl>``, ``EP_INF_<lvl>``, ``EP_SUP_S1`` (whole O-grid layers, centrally
    symmetric, so their node mean is the endplate centre), or, where the cohort's endplates are rim bands
    (``endplate_full_*`` given) and the means are given (``mean_hex`` (n_nodes, 3) and ``mean_tri`` (n_vertices,
    3) mm), the layer's nodes nearest to the rim band on the means; rims = the outer ring of those layers;
    femoral heads and pubic symphysis = the surface nodes carrying the cohort's landmark vertices; body =
    nodes of the ``V_<lvl>_*`` hexes.  Part labels: body nodes ``body_<lvl>``, disc nodes ``disc`` (appended
    to the cohort's part names), surface nodes their vertex's label.
    """
    n_hex = template.n_hex_nodes
    sv = np.asarray(template.surface_vertex)
    order = np.argsort(sv, kind="stable")

    def surface_nodes(vertices: np.ndarray, name: str) -> np.ndarray:
        v = np.asarray(vertices)
        pos = np.searchsorted(sv, v, sorter=order)
        pos = np.clip(pos, 0, len(sv) - 1)
        found = sv[order[pos]] == v
        if not found.all():
            raise ValueError(
                f"hex landmarks: {int((~found).sum())} vertices of {name} are not surface nodes of the template"
            )
        return n_hex + order[pos]

    outer = np.asarray(template.grid.outer)
    ns = template.nsets
    sup = {lv: ns[f"EP_SUP_{lv}"] for lv in (*LEVELS, "S1")}
    inf = {lv: ns[f"EP_INF_{lv}"] for lv in LEVELS}
    full_sup, full_inf = {}, {}
    if landmarks.endplate_full_sup and mean_hex is not None and mean_tri is not None:
        # the cohort's endplate planes are rim bands (real, concave endplates): the hex plane likewise, on the
        # layer's nodes nearest to the rim band on the mean, not on the whole layer, which dips into the
        # concavity, nor on its outer ring, which follows the body's outline past the ring apophysis
        full_sup, full_inf = sup, inf
        sup = {
            lv: _nearest_layer_nodes(v, mean_hex[v], mean_tri[landmarks.endplate_sup[lv]]) for lv, v in full_sup.items()
        }
        inf = {
            lv: _nearest_layer_nodes(v, mean_hex[v], mean_tri[landmarks.endplate_inf[lv]]) for lv, v in full_inf.items()
        }
    body = {}
    for lv in LEVELS:
        sets = [
            template.elsets[k] for k in template.elsets if k.startswith(f"V_{lv}_") and template.elset_kind[k] == "hex"
        ]
        if not sets:
            raise ValueError(f"hex landmarks: the template has no V_{lv}_* element set")
        body[lv] = np.unique(template.hexes[np.concatenate(sets)])
    names = tuple(landmarks.part_names) + ("disc",)
    part = np.full(template.n_nodes, len(names) - 1, dtype=np.int16)
    part[n_hex:] = landmarks.part[sv]
    for lv, nodes in body.items():
        part[nodes] = names.index(f"body_{lv}") if f"body_{lv}" in names else len(names) - 1
    return Landmarks(
        part=part,
        part_names=names,
        endplate_sup=sup,
        endplate_inf=inf,
        rim_sup={lv: v[outer] for lv, v in (full_sup or sup).items()},
        rim_inf={lv: v[outer] for lv, v in (full_inf or inf).items()},
        femoral_head={k: surface_nodes(v, f"femoral_head[{k}]") for k, v in landmarks.femoral_head.items()},
        body=body,
        pubic_symphysis=surface_nodes(landmarks.pubic_symphysis, "pubic_symphysis"),
        meta={"source": "hex template node sets", **landmarks.meta},
        endplate_full_sup=full_sup,
        endplate_full_inf=full_inf,
    )


# ------------------------------------------------------------------------------------------ measure
def measure_shard(
    tri: np.ndarray,
    hexp: np.ndarray,
    weights: np.ndarray,
    model_ids: np.ndarray,
    tri_landmarks: Landmarks,
    hex_lm: Landmarks,
    **measure_kw,
) -> tuple[Columns, Columns]:
    """Parameters of given coordinates (e.g. a shard read back from the store) on the triangulated points,
    and their difference to the hex points: (params: model_id, w1..wm [SD], every parameter of ``measure``;
    tri_vs_hex: per numeric parameter, max and mean |tri - hex| over the models, in its unit)."""
    w = np.asarray(weights, dtype=np.float64)
    if len(w) != len(tri) or len(w) != len(hexp) or len(w) != len(model_ids):
        raise ValueError(
            f"shard arrays disagree on the model count: weights {len(w)}, tri {len(tri)}, "
            f"hex {len(hexp)}, ids {len(model_ids)}"
        )
    p_tri = measure_columns(tri, tri_landmarks, **measure_kw)
    p_hex = measure_columns(hexp, hex_lm, **measure_kw)
    return _params_table(w, model_ids, p_tri), _param_diff(p_tri, p_hex)


def shard_models_of(path, shard: int) -> tuple[np.ndarray, np.ndarray]:
    """(model IDs (S,), weights (S, m) in SD) of ``shard`` from the store's own metadata (not the config)."""
    attrs = dict(zarr.open_group(str(path), mode="r").attrs)
    start, stop = shard_range(int(shard), attrs["shard_models"], attrs["n_models"])
    ids = np.arange(start, stop)
    return ids, weights_of(ids, attrs["n_modes"], attrs["levels"])


def run_shard_job(
    store,
    shard: int,
    inputs: dict,
    outputs: dict,
    settings: dict,
    measure_settings: dict,
    log=None,
) -> dict:
    """The ``sample_shard`` job: one pass over ``shard`` of ``store`` and its per-shard files.

    inputs: paths ``ssm``, ``hex_ssm``, ``template``, ``cohort``; outputs: paths ``quality``, ``params``,
    ``tri_vs_hex``, ``record`` (written last: the job's completion mark).  settings: the config's ``store``
    block (``repair``, ``fail_on_unrepaired``); measure_settings: its ``measure`` block.  Returns the record
    (the store's sidecar plus timings in s, encode CPU s, stored bytes and model counts)."""
    import json
    from pathlib import Path

    from numcodecs import blosc

    # the rule has threads: 1 (Snakemake sets OMP/OpenBLAS threads to it; blosc has its own pool)
    blosc.set_nthreads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    store = Path(store)
    ids, weights = shard_models_of(store, shard)  # the store's own grid, not the config's
    template = HexTemplate.load(inputs["template"])
    landmarks = Landmarks.from_cohort(inputs["cohort"])  # the index sets only, not the patients' meshes
    ssm, hex_ssm = SSM.load(inputs["ssm"], weights.shape[1]), HexSSM.load(inputs["hex_ssm"])
    writer = ShardWriter(store, shard)
    batch = -(-DEFAULT_CHUNK // writer.chunk) * writer.chunk  # whole store chunks per batch
    t_load, c_load = time.perf_counter(), time.process_time()
    try:
        quality, params, diff, timing = process_shard(
            ssm,
            hex_ssm,
            template,
            weights,
            ids,
            landmarks,
            hex_landmarks(template, landmarks, hex_ssm.mean, ssm.mean),
            writer=writer,
            batch=batch,
            repair=settings["repair"],
            log=log,
            vertical=measure_settings["vertical_axis"],
            assumed_age=measure_settings["assumed_age"],
            c7_proxy=measure_settings["c7_proxy"],
        )
        unrepaired = np.flatnonzero(quality["invalid_after"] > 0)
        if len(unrepaired) and settings["fail_on_unrepaired"]:
            raise RuntimeError(
                f"shard {shard}: {len(unrepaired)} models keep inverted hexes after repair: "
                + "; ".join(str(e) for e in quality["repair_error"][unrepaired[:5]])
            )
    except BaseException:
        writer.abort()
        raise
    t1, c1 = time.perf_counter(), time.process_time()
    record = writer.close()
    for table, key, fmt in ((quality, "quality", "%.6g"), (params, "params", "%.6f"), (diff, "tri_vs_hex", "%.6g")):
        pd.DataFrame(table).to_csv(outputs[key], index=False, float_format=fmt)
    wall = time.perf_counter() - t0
    record.update(
        timing,
        load_s=t_load - t0,
        load_cpu_s=c_load - c0,
        close_s=time.perf_counter() - t1,
        close_cpu_s=time.process_time() - c1,  # index, renames, weights, sidecar and the three CSV files
        encode_cpu_s=writer.encode_cpu_s,
        stored_bytes=writer.stored_bytes,
        # per node of the models held (tri + whole hex model, its surface nodes counted though stored once)
        stored_nodes=len(ids) * (writer.n_nodes["tri/points"] + writer.n_hex_nodes),
        wall_s=wall,
        models_per_s=len(ids) / wall,
        models_inverted=int((quality["invalid_before"] > 0).sum()),
        models_distracted=int((np.asarray(quality.get("distraction_mm", 0)) > 0).sum()),
        models_repaired=int(quality["repaired"].sum()),
        models_unrepaired=len(unrepaired),
    )
    with open(outputs["record"], "w") as fh:
        json.dump(record, fh, indent=1)
    if log is not None:
        log.info(
            "shard %d: models %d-%d, %d discs opened, %d with inverted hexes, %d repaired, %d unrepaired; "
            "%.1f s (%.1f models/s), %.2f B/node; largest |tri - hex|: %s",
            shard,
            ids[0],
            ids[-1],
            record["models_distracted"],
            record["models_inverted"],
            record["models_repaired"],
            len(unrepaired),
            wall,
            record["models_per_s"],
            record["stored_bytes"] / record["stored_nodes"],
            _largest_differences(diff, 3),
        )
    return record


def _largest_differences(diff: Columns, n: int) -> list[dict]:
    """The n parameters with the largest max |tri - hex| (NaN last), rounded to 4 decimals, for the log."""
    largest = np.asarray(diff["max_abs_diff"], dtype=float)
    top = np.argsort(np.where(np.isnan(largest), -np.inf, -largest), kind="stable")[:n]
    return [{k: (round(float(v[i]), 4) if k != "parameter" else v[i]) for k, v in diff.items()} for i in top]
