"""What a personalization fits: the parameters a target may name, the pelvic identity PI = PT + SS that a set
of targets must satisfy, and ``f(x)``, the measured parameters of the SSM shape of weights x (and a sagittal
posture), evaluated on the landmark vertices only: 18k of 81k vertices on the default cohort, where a batch
of 200 models measures in 0.5 s against 1.0 s on the whole mesh (benchmarks/bench_personalize.py).
Millimetres and degrees."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from spinecohort.cohort.landmarks import Landmarks
from spinecohort.measure.spinopelvic import UNITS, measure
from spinecohort.ssm.model import SSM

#: the parameters every personalization fits at least (PI = PT + SS: two independent pelvic angles)
CORE_PARAMETERS = ("PI", "PT", "SS", "LL")
#: largest tolerated |PI - (PT + SS)| (deg) in a set of targets that gives all three
PELVIC_IDENTITY_TOL_DEG = 0.5


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
