"""Personalized models of a whole cohort: both methods for every patient with their parameter errors and
shape distances, the ``personalize:`` settings of the configuration, and the checked hex coordinates of one
personalized model."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd

from spinecohort.cohort.landmarks import Landmarks
from spinecohort.measure.spinopelvic import measure
from spinecohort.personalize.fit import PersonalizationModel, project_shapes
from spinecohort.personalize.parameters import ParameterFunction, pose
from spinecohort.ssm.model import SSM
from spinecohort.ssm.procrustes import apply_transform, kabsch

log = logging.getLogger(__name__)

#: the two methods of `personalize_cohort`, in the order of its table
METHODS = ("fit", "projection")


def shape_distances(model: np.ndarray, target: np.ndarray) -> dict[str, np.ndarray]:
    """Per-vertex distances (mm) between corresponding vertices of models and targets (B, N, 3).

    ``dist_*``: after the best rigid (Kabsch) superposition of each model on its target - shape only, as the
    GPA compares shapes (a fitted model stands at its patient's PT, the aligned shape at the GPA's pose);
    ``dist_placed_*``: as the models lie.  Mean and max over the vertices, (B,) arrays each.
    """
    model = np.asarray(model, dtype=float)
    target = np.asarray(target, dtype=float)
    d_placed = np.linalg.norm(model - target, axis=2)
    r, s, t = kabsch(model, target)
    d_rigid = np.linalg.norm(apply_transform(model, r, s, t) - target, axis=2)
    return {
        "dist_mean_mm": d_rigid.mean(1),
        "dist_max_mm": d_rigid.max(1),
        "dist_placed_mean_mm": d_placed.mean(1),
        "dist_placed_max_mm": d_placed.max(1),
    }


# ------------------------------------------------------------------------------------- whole cohort


@dataclass
class Settings:
    """The ``personalize:`` block of the configuration (docs/reference/config.md)."""

    parameters: list[str]
    weights: dict
    n_modes: int
    bound_sd: float = 3.0
    posture_deg: float = 0.0
    prior: float = 0.05
    surrogate_samples: int = 1024
    seed: int = 0

    @classmethod
    def from_config(cls, block: dict, grid_modes: int) -> Settings:
        p = dict(block)
        n = p.pop("n_modes") or grid_modes
        if n > grid_modes:
            raise ValueError(
                f"personalize.n_modes ({n}) exceeds grid.n_modes ({grid_modes}): the hex SSM has "
                f"fields for {grid_modes} modes only"
            )
        targets = p.pop("targets")
        return cls(parameters=list(targets), weights=dict(targets), n_modes=int(n), **p)


def build_model(
    ssm: SSM, landmarks: Landmarks, settings: Settings, measure_kw: dict | None = None
) -> PersonalizationModel:
    fn = ParameterFunction.from_ssm(
        ssm, landmarks, settings.n_modes, posture=settings.posture_deg > 0, **(measure_kw or {})
    )
    return PersonalizationModel(
        fn,
        settings.parameters,
        settings.weights,
        settings.bound_sd,
        settings.prior,
        settings.surrogate_samples,
        settings.seed,
        settings.posture_deg,
    )


def model_shapes(ssm: SSM, weights: np.ndarray, posture_deg: np.ndarray) -> np.ndarray:
    """Triangulated shapes (B, N, 3) mm of weights (B, k) SD, turned by their posture angles (B,) deg."""
    return pose(ssm.sample(np.atleast_2d(weights)), np.asarray(posture_deg, dtype=float))


def personalize_cohort(
    ssm: SSM,
    landmarks: Landmarks,
    ids: list[str],
    targets: pd.DataFrame,
    aligned: np.ndarray,
    settings: Settings,
    measure_kw: dict | None = None,
) -> tuple[pd.DataFrame, dict]:
    """Both methods for every patient -> (table, info).

    targets: patient parameter table with an ``ID`` column (deg / mm; NaN = not given); aligned: (P, N, 3)
    the patients' GPA-aligned shapes in ``ids`` order.  The table has one row per patient and method:
    ``ID, method, b1..bk, posture_deg``, ``<p>_target``, ``<p>_achieved``, ``<p>_error`` (achieved - target)
    per fitted parameter, the distances of :func:`shape_distances`, ``at_bound``, ``evaluations``, ``fit_s``.
    info: surrogate errors, timings, and the parameter error of the aligned shapes themselves.
    """
    measure_kw = dict(measure_kw or {})
    params, k = settings.parameters, settings.n_modes
    tab = targets.set_index(targets["ID"].astype(str))
    missing = [i for i in ids if i not in tab.index]
    if missing:
        raise ValueError(f"personalize: no target parameters for patients {', '.join(missing)}")
    absent = [p for p in params if p not in tab.columns]
    if absent:
        raise ValueError(f"personalize: the parameter table has no column {', '.join(absent)}")
    if aligned.shape != (len(ids), *ssm.mean.shape):
        raise ValueError(
            f"personalize: aligned shapes {aligned.shape} do not match {len(ids)} patients x {ssm.mean.shape}"
        )
    t0 = time.perf_counter()
    model = build_model(ssm, landmarks, settings, measure_kw)
    t_sur = time.perf_counter() - t0

    fit_w, fit_pose, fit_rows = np.zeros((len(ids), k)), np.zeros(len(ids)), []
    t1 = time.perf_counter()
    for i, pid in enumerate(ids):  # one optimisation per patient
        ts = time.perf_counter()
        tgt = {p: float(tab.at[pid, p]) for p in params if np.isfinite(float(tab.at[pid, p]))}
        res = model.fit(tgt)
        fit_w[i], fit_pose[i] = res.weights, res.posture_deg
        fit_rows.append({"at_bound": res.at_bound, "evaluations": res.evaluations, "fit_s": time.perf_counter() - ts})
        log.info(
            "%s fit: b = %s SD, posture %.2f deg; %s",
            pid,
            np.round(res.weights, 3).tolist(),
            res.posture_deg,
            ", ".join(f"{p} {tgt.get(p, np.nan):.2f}->{res.achieved[p]:.2f}" for p in params),
        )
    t_fit = time.perf_counter() - t1

    t2 = time.perf_counter()
    proj_w, raw = project_shapes(ssm, aligned, k, settings.bound_sd)
    t_proj = time.perf_counter() - t2
    proj_rows = [{"at_bound": int(np.sum(np.abs(r) >= settings.bound_sd)), "evaluations": 0, "fit_s": 0.0} for r in raw]

    fn = model.fn
    rows = []
    for method, w, ang, extra in (
        ("fit", fit_w, fit_pose, fit_rows),
        ("projection", proj_w, np.zeros(len(ids)), proj_rows),
    ):
        x = np.c_[w, ang] if fn.posture else w
        achieved = fn(x, params)  # one batch: every patient's model
        dist = shape_distances(model_shapes(ssm, w, ang), aligned)
        for i, pid in enumerate(ids):
            row = {"ID": pid, "method": method, **{f"b{j + 1}": w[i, j] for j in range(k)}, "posture_deg": ang[i]}
            for j, p in enumerate(params):
                t = float(tab.at[pid, p])
                row.update({f"{p}_target": t, f"{p}_achieved": achieved[i, j], f"{p}_error": achieved[i, j] - t})
            row.update({name: float(v[i]) for name, v in dist.items()})
            row.update(extra[i])
            rows.append(row)
    # the floor under both methods: the patients' own aligned shapes (every mode, no fit, GPA pose)
    own_err = measure(aligned, landmarks, **measure_kw)[params].to_numpy(float) - tab.loc[ids, params].to_numpy(float)
    info = {
        "surrogate_rms_error": model.surrogate.rms_error,
        "surrogate_s": t_sur,
        "fit_s": t_fit,
        "projection_s": t_proj,
        "n_patients": len(ids),
        "n_modes": k,
        "parameters": list(params),
        "posture_deg": settings.posture_deg,
        "aligned_shape_error_mean_abs": dict(zip(params, np.nanmean(np.abs(own_err), axis=0).tolist())),
        "aligned_shape_error_max_abs": dict(zip(params, np.nanmax(np.abs(own_err), axis=0).tolist())),
    }
    return pd.DataFrame(rows), info


# ------------------------------------------------------------------------------------------ FE models


def personalized_hex(
    template, hex_ssm, weights: np.ndarray, posture_deg: float = 0.0, name: str = "model"
) -> tuple[np.ndarray, dict]:
    """Hex model coordinates (n_nodes, 3) mm of one personalized model, checked and repaired exactly as the
    virtual models are (:func:`models.hex_points_checked`), then turned by its posture (a rotation changes
    no Jacobian).  A model that cannot be repaired raises RepairError naming ``name``."""
    from spinecohort.fe.models import hex_points_checked
    from spinecohort.mesh.repair import RepairError

    w = np.asarray(weights, dtype=float)
    if w.shape[0] > hex_ssm.fields.shape[0]:
        raise ValueError(f"{name}: {w.shape[0]} weights but the hex SSM has {hex_ssm.fields.shape[0]} modes")
    try:
        pts, report = hex_points_checked(template, hex_ssm, w)
    except RepairError as exc:
        raise RepairError(f"{name} (weights {np.round(w, 3).tolist()} SD) cannot be repaired: {exc}") from exc
    return pose(pts[None], [posture_deg])[0], report
