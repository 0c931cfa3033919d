"""The two ways to find mode weights for a patient: the fit to parameter targets (a quadratic surrogate for the
start, bounded trust-region least squares on the real measurement to refine) and the projection of the
patient's own aligned shape on the modes.  Weights in SD units, parameters in deg / mm."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import qmc

from spinecohort.personalize.parameters import (
    CORE_PARAMETERS,
    ParameterFunction,
    complete_pelvic_targets,
    fittable_parameters,
)
from spinecohort.ssm.model import SSM

log = logging.getLogger(__name__)


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
