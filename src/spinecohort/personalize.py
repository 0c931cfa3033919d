"""Patient-personalized models: SSM mode weights whose model matches a patient's spinopelvic parameters.

Two ways to personalize (docs/personalization.md):

* **fit** (parameter-based, the seed's Figure 8 pipeline): find continuous weights ``b`` (SD units,
  within ``±bound_sd``) minimising the weighted parameter misfit
  ``sum_p (omega_p (f_p(b) - t_p))^2 + prior^2 |b|^2`` where ``f`` is the real measurement
  (``measure.measure``) of the SSM shape ``mean + sum_i sqrt(d_i) phi_i b_i``.  A quadratic surrogate of ``f``,
  fitted once to a quasi-random batch of sampled models, gives the start; bounded trust-region least squares
  (``scipy.optimize.least_squares``, ``trf``) on the real measurement refines it, with a central-difference
  Jacobian evaluated as one batch of ``2k + 1`` models.  The small ``prior`` term picks, among weight vectors
  that match the parameters equally well, the one closest to the mean (the most probable under the SSM's
  Gaussian): a handful of parameters does not determine ``k`` weights.
* **projection** (image-based): least-squares projection of the patient's own GPA-aligned shape on the first
  ``k`` modes, clipped to ``±bound_sd``.  Needs the patient's 3-D shape; matches the shape, not the parameters.

Only the landmark vertices enter the measurement, so the SSM is restricted to them once
(:class:`ParameterFunction`, 18k of 81k vertices on the default cohort): sampling a batch no longer costs the
whole mesh (200 models: 0.5 s instead of 1.0 s on the loaded 2-core machine; the 13-model Jacobian batch of
a fit iteration 0.11 s instead of 0.15 s).

PI = PT + SS holds identically for every measured model, so a set of targets that gives all three must
satisfy it too (:func:`complete_pelvic_targets` checks it, and derives the third when two are given).
Millimetres and degrees throughout.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.stats import qmc

from spinecohort.cohort.landmarks import Landmarks
from spinecohort.measure.spinopelvic import UNITS, measure
from spinecohort.ssm.model import SSM
from spinecohort.ssm.procrustes import apply_transform, kabsch

log = logging.getLogger(__name__)

#: the parameters every personalization fits at least (PI = PT + SS: two independent pelvic angles)
CORE_PARAMETERS = ("PI", "PT", "SS", "LL")
#: largest tolerated |PI - (PT + SS)| (deg) in a set of targets that gives all three
PELVIC_IDENTITY_TOL_DEG = 0.5
METHODS = ("fit", "projection")


# ------------------------------------------------------------------------------------------- targets


def fittable_parameters() -> list[str]:
    """Numeric, continuous outputs of :func:`measure.measure` a target may name (GAP points excluded)."""
    return [
        c for c, u in UNITS.items() if u in ("deg", "mm", "%") and c != "PI_identity_err" and c != "endplate_rms_max"
    ]


def complete_pelvic_targets(
    targets: dict[str, float], tol_deg: float = PELVIC_IDENTITY_TOL_DEG, source: str = "targets"
) -> dict[str, float]:
    """Targets with the pelvic identity PI = PT + SS enforced.

    Two of PI, PT, SS given: the third is derived (a model cannot have any other value).  All three given:
    they must agree within ``tol_deg`` (a measured set agrees to 1e-6 deg), else ValueError naming
    ``source`` - no model can reach an inconsistent triple, and the fit would split the contradiction
    arbitrarily.  Unknown parameter names and non-finite values raise ValueError too.
    """
    allowed = set(fittable_parameters())
    out = {}
    for k, v in targets.items():
        if k not in allowed:
            raise ValueError(
                f"{source}: '{k}' is not a parameter that can be fitted; choose from {', '.join(sorted(allowed))}"
            )
        if v is None or not np.isfinite(float(v)):
            raise ValueError(f"{source}: target {k} = {v} is not a finite number")
        out[k] = float(v)
    have = [p for p in ("PI", "PT", "SS") if p in out]
    if len(have) == 3:
        gap = out["PI"] - out["PT"] - out["SS"]
        if abs(gap) > tol_deg:
            raise ValueError(
                f"{source}: PI ({out['PI']:g}) must equal PT + SS ({out['PT']:g} + {out['SS']:g} = "
                f"{out['PT'] + out['SS']:g}) within {tol_deg:g} deg; give two of the three"
            )
    elif len(have) == 2:
        if "PI" not in out:
            out["PI"] = out["PT"] + out["SS"]
        elif "PT" not in out:
            out["PT"] = out["PI"] - out["SS"]
        else:
            out["SS"] = out["PI"] - out["PT"]
    return out


# ------------------------------------------------------------------------------- measurement function


def landmark_vertices(landmarks: Landmarks) -> np.ndarray:
    """Sorted indices of every vertex :func:`measure.measure` reads (endplates, rims, femoral heads, symphysis)."""
    sets = [
        landmarks.endplate_sup,
        landmarks.endplate_inf,
        landmarks.rim_sup,
        landmarks.rim_inf,
        landmarks.femoral_head,
        {"": landmarks.pubic_symphysis},
    ]
    return np.unique(np.concatenate([np.asarray(v).ravel() for s in sets for v in s.values()]))


def restrict_landmarks(landmarks: Landmarks, vertices: np.ndarray) -> Landmarks:
    """``landmarks`` renumbered onto the subset ``vertices`` (sorted, containing every landmark vertex).

    Body sets keep only their vertices inside the subset (their endplates): measurement does not read them.
    """
    vertices = np.asarray(vertices)

    def remap(idx: np.ndarray) -> np.ndarray:
        pos = np.searchsorted(vertices, idx)
        if np.any(pos >= len(vertices)) or np.any(vertices[np.minimum(pos, len(vertices) - 1)] != idx):
            raise ValueError("restrict_landmarks: a landmark vertex is not in the subset")
        return pos

    def inside(idx: np.ndarray) -> np.ndarray:
        pos = np.minimum(np.searchsorted(vertices, idx), len(vertices) - 1)
        return pos[vertices[pos] == idx]

    return Landmarks(
        part=landmarks.part[vertices],
        part_names=landmarks.part_names,
        endplate_sup={k: remap(v) for k, v in landmarks.endplate_sup.items()},
        endplate_inf={k: remap(v) for k, v in landmarks.endplate_inf.items()},
        rim_sup={k: remap(v) for k, v in landmarks.rim_sup.items()},
        rim_inf={k: remap(v) for k, v in landmarks.rim_inf.items()},
        femoral_head={k: remap(v) for k, v in landmarks.femoral_head.items()},
        body={k: inside(v) for k, v in landmarks.body.items()},
        pubic_symphysis=remap(landmarks.pubic_symphysis),
        meta=dict(landmarks.meta),
    )


def sagittal_rotation(theta_deg: np.ndarray) -> np.ndarray:
    """Rotations (B, 3, 3) by ``theta_deg`` (B,) about the frame's left-right x axis (RAS).

    Positive angles turn the top of the model forwards (+y), which lowers PT and raises SS by the same angle
    when the patient's left-right axis is x: a change of posture, not of shape.
    """
    t = np.deg2rad(np.asarray(theta_deg, dtype=float))
    c, s = np.cos(t), np.sin(t)
    z, o = np.zeros_like(t), np.ones_like(t)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, s], -1), np.stack([z, -s, c], -1)], -2)


def pose(points: np.ndarray, theta_deg: np.ndarray) -> np.ndarray:
    """Points (B, N, 3) mm turned by :func:`sagittal_rotation` about the SSM origin (the GPA centroid)."""
    return np.einsum("bij,bnj->bni", sagittal_rotation(theta_deg), points)


@dataclass
class ParameterFunction:
    """``f(x)``: measured parameters of the SSM shapes of a batch of variables, on the landmark vertices only.

    x = (b_1..b_k) weights in SD, plus, if ``posture``, a sagittal rotation theta in degrees
    (:func:`pose`).  mean (n, 3) mm and fields (k, n, 3) mm per SD are the SSM restricted to the landmark
    vertices; ``measure_kw`` go to :func:`measure.measure` (vertical, c7_proxy).
    """

    mean: np.ndarray
    fields: np.ndarray
    landmarks: Landmarks
    posture: bool = False
    measure_kw: dict = field(default_factory=dict)
    evaluations: int = 0

    @classmethod
    def from_ssm(
        cls, ssm: SSM, landmarks: Landmarks, n_modes: int, posture: bool = False, **measure_kw
    ) -> ParameterFunction:
        if not 1 <= n_modes <= ssm.n_modes:
            raise ValueError(f"n_modes must be between 1 and the SSM's {ssm.n_modes} modes, got {n_modes}")
        landmarks.validate(ssm.mean.shape[0], "personalize landmarks")
        idx = landmark_vertices(landmarks)
        return cls(
            ssm.mean[idx],
            ssm.deformation_fields(n_modes)[:, idx],
            restrict_landmarks(landmarks, idx),
            posture,
            dict(measure_kw),
        )

    @property
    def n_modes(self) -> int:
        return int(self.fields.shape[0])

    @property
    def n_vars(self) -> int:
        return self.n_modes + int(self.posture)

    def points(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, dtype=float))
        pts = self.mean + np.tensordot(x[:, : self.n_modes], self.fields, axes=(1, 0))
        return pose(pts, x[:, -1]) if self.posture else pts

    def table(self, x: np.ndarray) -> pd.DataFrame:
        """Every parameter of :func:`measure.measure` for variables (B, n_vars)."""
        pts = self.points(x)
        self.evaluations += len(pts)
        return measure(pts, self.landmarks, **self.measure_kw)

    def __call__(self, x: np.ndarray, parameters: list[str]) -> np.ndarray:
        """(B, P) values of ``parameters`` for variables (B, n_vars)."""
        return self.table(x)[list(parameters)].to_numpy(float)


# -------------------------------------------------------------------------------------------- surrogate


def _quadratic_features(x: np.ndarray) -> np.ndarray:
    """[1, x_i, x_i x_j (i <= j)] for variables (B, n) -> (B, 1 + n + n(n+1)/2)."""
    iu = np.triu_indices(x.shape[1])
    return np.hstack([np.ones((len(x), 1)), x, (x[:, :, None] * x[:, None, :])[:, iu[0], iu[1]]])


@dataclass
class QuadraticSurrogate:
    """Least-squares quadratic polynomial of each parameter in the variables, over the fitting box."""

    parameters: list[str]
    coef: np.ndarray  # (n_features, P)
    n_vars: int
    rms_error: dict  # parameter -> RMS residual on held-out samples (deg / mm)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return _quadratic_features(np.atleast_2d(x)) @ self.coef

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """(P, n) derivative at one variable vector x (n,)."""
        n = self.n_vars
        h = np.zeros((len(self.parameters), n, n))
        iu = np.triu_indices(n)
        h[:, iu[0], iu[1]] = self.coef[1 + n :].T
        # d/dx (x^T H x) with H upper triangular = (H + H^T) x
        return self.coef[1 : 1 + n].T + np.einsum("pij,j->pi", h + h.transpose(0, 2, 1), x)


def fit_surrogate(
    fn: ParameterFunction, parameters: list[str], half_width: np.ndarray, n_samples: int, seed: int = 0
) -> tuple[QuadraticSurrogate, np.ndarray, np.ndarray]:
    """Quadratic surrogate of ``parameters`` from ``n_samples`` scrambled-Sobol models in the box
    ``[-half_width, half_width]`` (n_vars,).

    A fifth of the samples is held out to report the surrogate's RMS error, then the final fit uses all.
    Returns the surrogate and the sampled variables (S, n) with their measured values (S, P) (they also
    serve as starting points).
    """
    n = fn.n_vars
    n_feat = 1 + n + n * (n + 1) // 2
    if n_samples < 2 * n_feat:
        raise ValueError(f"surrogate_samples must be at least {2 * n_feat} for {n} variables, got {n_samples}")
    m = int(np.ceil(np.log2(n_samples)))  # Sobol' balance needs a power of two; keep the first n_samples
    x = (2.0 * qmc.Sobol(n, scramble=True, seed=seed).random_base2(m)[:n_samples] - 1.0) * half_width
    y = fn(x, parameters)
    ok = np.all(np.isfinite(y), axis=1)
    # Robust: a few corner models (all weights near +-3 SD and a large rotation) put the pubic symphysis
    # behind S1, so the measurement flips the patient frame and PI, SS, LL change sign there.  They are not
    # spines; a first fit finds them (residual > 8 robust SDs in any parameter) and the second ignores them.
    feat = _quadratic_features(x)
    coef, *_ = np.linalg.lstsq(feat[ok], y[ok], rcond=None)
    r = np.where(ok[:, None], feat @ coef - np.where(ok[:, None], y, 0.0), np.inf)
    sigma = 1.4826 * np.median(np.abs(r[ok]), axis=0) + 1e-12
    ok &= np.all(np.abs(r) <= 8.0 * sigma, axis=1)
    x, y, feat = x[ok], y[ok], feat[ok]
    n_test = len(x) // 5
    coef, *_ = np.linalg.lstsq(feat[n_test:], y[n_test:], rcond=None)
    rms = np.sqrt(np.mean((feat[:n_test] @ coef - y[:n_test]) ** 2, axis=0))
    coef, *_ = np.linalg.lstsq(feat, y, rcond=None)
    if n_samples - len(x):
        log.info(
            "surrogate: %d of %d sampled models left out (frame flipped or not finite)", n_samples - len(x), n_samples
        )
    return QuadraticSurrogate(list(parameters), coef, n, {p: float(e) for p, e in zip(parameters, rms)}), x, y


# ------------------------------------------------------------------------------------------------ fit


@dataclass
class FitResult:
    weights: np.ndarray  # (k,) SD
    posture_deg: float  # sagittal rotation (0 when posture is not fitted)
    achieved: dict  # parameter -> value (deg / mm)
    cost: float  # weighted squared misfit (without the prior)
    evaluations: int  # models measured by the direct refinement
    at_bound: int  # weights at +-bound_sd


class PersonalizationModel:
    """Fits weights (and, optionally, the posture) to targets; the surrogate is built once and reused.

    parameters: names fitted (must include PI, PT, SS, LL); weights: parameter -> omega (1/deg, 1/mm;
    default 1); bound_sd: box of the mode weights; posture_deg: box of the sagittal rotation (0 = no
    posture variable); prior: residual per SD of weight (a tie-breaker towards the mean).
    """

    def __init__(
        self,
        fn: ParameterFunction,
        parameters: list[str],
        weights: dict[str, float] | None = None,
        bound_sd: float = 3.0,
        prior: float = 0.05,
        surrogate_samples: int = 1024,
        seed: int = 0,
        posture_deg: float = 0.0,
        fd_step: float = 1e-3,
    ):
        missing = [p for p in CORE_PARAMETERS if p not in parameters]
        if missing:
            raise ValueError(
                f"personalize: the fitted parameters must include {', '.join(CORE_PARAMETERS)}; "
                f"missing {', '.join(missing)}"
            )
        unknown = sorted(set(parameters) - set(fittable_parameters()))
        if unknown:
            raise ValueError(
                f"personalize: {', '.join(unknown)} cannot be fitted; choose from {', '.join(fittable_parameters())}"
            )
        weights = dict(weights or {})
        extra = sorted(set(weights) - set(parameters))
        if extra:
            raise ValueError(f"personalize: weights given for parameters not fitted: {', '.join(extra)}")
        if bound_sd <= 0 or prior < 0 or fd_step <= 0 or posture_deg < 0:
            raise ValueError("personalize: need bound_sd > 0, prior >= 0, fd_step > 0, posture_deg >= 0")
        if fn.posture != (posture_deg > 0):
            raise ValueError("personalize: the measurement function's posture flag must match posture_deg > 0")
        self.fn = fn
        self.parameters = list(parameters)
        self.omega = np.array([float(weights.get(p, 1.0)) for p in self.parameters])
        if np.any(self.omega <= 0):
            raise ValueError("personalize: every parameter weight must be positive")
        k = fn.n_modes
        self.half_width = np.r_[np.full(k, float(bound_sd)), [float(posture_deg)] * fn.posture]
        self.bound_sd = float(bound_sd)
        # prior on the weights only: the posture is free within its box
        self.prior_diag = np.r_[np.full(k, float(prior)), [0.0] * fn.posture]
        self.fd_step = float(fd_step)
        t0 = time.perf_counter()
        self.surrogate, self.samples_x, self.samples_y = fit_surrogate(
            fn, self.parameters, self.half_width, surrogate_samples, seed
        )
        log.info(
            "surrogate: %d models in %.2f s; held-out RMS error %s",
            len(self.samples_x),
            time.perf_counter() - t0,
            {p: round(e, 3) for p, e in self.surrogate.rms_error.items()},
        )

    def fit(self, targets: dict[str, float]) -> FitResult:
        """Variables within the box whose measured model best matches ``targets`` (parameter -> deg / mm)."""
        targets = complete_pelvic_targets(targets)
        unknown = sorted(set(targets) - set(self.parameters))
        if unknown:
            raise ValueError(
                f"personalize: {', '.join(unknown)} not among the fitted parameters "
                f"({', '.join(self.parameters)}); add them to personalize.parameters"
            )
        t = np.array([targets.get(p, np.nan) for p in self.parameters])
        use = np.isfinite(t)
        if not use.any():
            raise ValueError("personalize: no finite target value")
        om, tt, pd_ = self.omega[use], t[use], self.prior_diag
        n, lo, hi = self.fn.n_vars, -self.half_width, self.half_width
        sur = self.surrogate

        def r_sur(x):
            return np.r_[om * (sur(x)[0, use] - tt), pd_ * x]

        def j_sur(x):
            return np.r_[om[:, None] * sur.jacobian(x)[use], np.diag(pd_)]

        # starts: the mean and the best sampled model (its true misfit is known); each solved on the
        # surrogate, then the candidate with the lowest true misfit is refined on the real measurement
        cost_samples = np.sum((om * (self.samples_y[:, use] - tt)) ** 2, axis=1)
        starts = [np.zeros(n), self.samples_x[int(np.argmin(cost_samples))]]
        cands = np.array(
            [least_squares(r_sur, x0, jac=j_sur, bounds=(lo, hi), method="trf").x for x0 in starts] + starts
        )
        true = self.fn(cands, self.parameters)[:, use]
        cost = np.sum((om * (true - tt)) ** 2, axis=1) + np.sum((pd_ * cands) ** 2, axis=1)
        x0 = cands[int(np.argmin(cost))]

        n0 = self.fn.evaluations
        step = self.fd_step * self.half_width / self.bound_sd  # 1e-3 SD, and 1e-3 deg per 1 SD of box
        cache: dict = {}

        def evaluate(x):
            key = x.tobytes()
            if key not in cache:
                # one batch: x, x + h e_i, x - h e_i (central differences, kept inside the box)
                hp, hm = np.minimum(step, hi - x), np.minimum(step, x - lo)
                y = self.fn(np.vstack([x, x + np.diag(hp), x - np.diag(hm)]), self.parameters)[:, use]
                cache.clear()
                cache[key] = (y[0], (y[1 : 1 + n] - y[1 + n :]).T / np.maximum(hp + hm, 1e-12))
            return cache[key]

        def r_true(x):
            return np.r_[om * (evaluate(x)[0] - tt), pd_ * x]

        def j_true(x):
            return np.r_[om[:, None] * evaluate(x)[1], np.diag(pd_)]

        res = least_squares(
            r_true,
            np.clip(x0, lo, hi),
            jac=j_true,
            bounds=(lo, hi),
            method="trf",
            xtol=1e-8,
            ftol=1e-10,
            gtol=1e-8,
            max_nfev=50,
        )
        x = res.x
        achieved = self.fn.table(x[None]).iloc[0]
        k = self.fn.n_modes
        return FitResult(
            x[:k].copy(),
            float(x[k]) if self.fn.posture else 0.0,
            {p: float(achieved[p]) for p in self.parameters},
            float(np.sum((om * (evaluate(x)[0] - tt)) ** 2)),
            self.fn.evaluations - n0,
            int(np.sum(np.abs(x[:k]) >= self.bound_sd * (1 - 1e-9))),
        )


# ----------------------------------------------------------------------------------------- projection


def project_shapes(ssm: SSM, shapes: np.ndarray, n_modes: int, bound_sd: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares mode weights (B, k) in SD of GPA-aligned shapes (B, N, 3) mm, clipped to ±bound_sd.

    The modes are orthonormal, so the least-squares fit is the projection ``Phi^T (x - mean) / sqrt(d)`` and
    the problem separates per mode: clipping each weight to the box is the exact box-constrained solution.
    Also returns the unclipped weights.
    """
    raw = ssm.project(shapes, n_modes)
    return np.clip(raw, -bound_sd, bound_sd), raw


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
    """The ``personalize:`` block of the configuration (docs/personalization.md)."""

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


# ----------------------------------------------------------------------------------- FE models, report


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


def error_summary(table: pd.DataFrame, parameters: list[str]) -> pd.DataFrame:
    """Per method and parameter: mean |error|, max |error| (unit of the parameter) and the bias."""
    rows = []
    for method, g in table.groupby("method", sort=False):
        for p in parameters:
            e = g[f"{p}_error"].to_numpy(float)
            e = e[np.isfinite(e)]
            rows.append(
                {
                    "method": method,
                    "parameter": p,
                    "unit": UNITS.get(p, ""),
                    "n": len(e),
                    "mean_abs_error": np.abs(e).mean(),
                    "max_abs_error": np.abs(e).max(),
                    "bias": e.mean(),
                }
            )
    return pd.DataFrame(rows)


def report_markdown(table: pd.DataFrame, info: dict) -> str:
    """The personalization report: error table per method, shape distances, Jacobian checks, run times."""
    params = info["parameters"]
    summ = error_summary(table, params)
    lines = [
        f"# Personalization report ({info['n_patients']} patients, {info['n_modes']} modes)",
        "",
        f"Fitted parameters: {', '.join(params)}; posture (sagittal rotation) box "
        f"±{info['posture_deg']:g} deg.  Errors are achieved - target, targets measured on each patient's "
        "own mesh.",
        "",
        "## Parameter error (mean / max |achieved - target|)",
        "",
        "| parameter | unit | fit mean | fit max | projection mean | projection max | aligned shape mean | "
        "aligned shape max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in params:
        f = summ[(summ.method == "fit") & (summ.parameter == p)].iloc[0]
        q = summ[(summ.method == "projection") & (summ.parameter == p)].iloc[0]
        lines.append(
            f"| {p} | {UNITS.get(p, '')} | {f.mean_abs_error:.3f} | {f.max_abs_error:.3f} | "
            f"{q.mean_abs_error:.3f} | {q.max_abs_error:.3f} | "
            f"{info['aligned_shape_error_mean_abs'][p]:.3f} | {info['aligned_shape_error_max_abs'][p]:.3f} |"
        )
    lines += [
        "",
        "The aligned-shape columns measure each patient's own GPA-aligned shape (every mode, no fit): "
        "what any model in the SSM frame inherits from the alignment (GPA removes posture, so PT and SS "
        "change; PI and LL do not).",
        "",
        "## Shape distance to the patient's aligned shape (mm)",
        "",
        "Per-vertex distance between corresponding vertices after a rigid superposition (shape only); "
        "in brackets as placed in the SSM frame.",
        "",
        "| method | mean of means | max of means | max of maxima | weights at ±bound |",
        "|---|---|---|---|---|",
    ]
    for method, g in table.groupby("method", sort=False):
        lines.append(
            f"| {method} | {g.dist_mean_mm.mean():.2f} ({g.dist_placed_mean_mm.mean():.2f}) | "
            f"{g.dist_mean_mm.max():.2f} | {g.dist_max_mm.max():.2f} ({g.dist_placed_max_mm.max():.2f}) | "
            f"{int(g.at_bound.sum())} |"
        )
    fit = table[table.method == "fit"]
    if "invalid_before" in fit:
        lines += [
            "",
            "## Hexahedral models (fit method, `personalized/<ID>.inp`)",
            "",
            f"{len(fit)} models; inverted hexes before repair in {int((fit.invalid_before > 0).sum())} "
            f"(total {int(fit.invalid_before.sum())}), after repair {int(fit.invalid_after.sum())}; "
            f"min scaled Jacobian after repair {fit.min_sj_after.min():.3f}.",
        ]
    sur = info["surrogate_rms_error"]
    lines += [
        "",
        "## Run",
        "",
        f"Surrogate (quadratic, held-out RMS error: {', '.join(f'{p} {e:.3f}' for p, e in sur.items())}) "
        f"{info['surrogate_s']:.1f} s; fits {info['fit_s']:.1f} s "
        f"({info['fit_s'] / max(info['n_patients'], 1):.2f} s per patient, "
        f"{fit.evaluations.mean():.0f} models measured each); projections {info['projection_s']:.2f} s.",
        "",
        "## Pros and cons, in numbers",
        "",
        f"- fit: parameters within {summ[summ.method == 'fit'].max_abs_error.max():.3f} (max over "
        f"parameters and patients), needs only the parameters (radiographs), but the shape is the most "
        f"probable one for them: {fit.dist_mean_mm.mean():.1f} mm mean distance to the patient.",
        f"- projection: shape {table[table.method == 'projection'].dist_mean_mm.mean():.1f} mm mean "
        f"distance, needs the patient's 3-D shape; parameters off by up to "
        f"{summ[summ.method == 'projection'].max_abs_error.max():.1f} (modes truncated, GPA posture).",
        "",
    ]
    return "\n".join(lines)
