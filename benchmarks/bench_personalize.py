"""Personalization speed: the measurement function on the landmark subset versus the whole mesh, the
surrogate, one fit per patient (fit method), and the projection of every patient.

Uses a finished run's results (default ``results``: ssm/ssm.npz, cohort/cohort.npz, ssm/aligned.npz,
patients/parameters.csv).  Prints models/s of both measurement paths and their ratio, the surrogate time, the
fit time per patient and the projection time.

Run: python benchmarks/bench_personalize.py [results] [n_patients]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.measure.spinopelvic import measure
from spinecohort.personalize.cohort import Settings, build_model
from spinecohort.personalize.fit import project_shapes
from spinecohort.personalize.parameters import CORE_PARAMETERS
from spinecohort.ssm.model import SSM


def best_of(f, n=3):
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(results: str = "results", n_patients: int = 10) -> None:
    r = Path(results)
    ssm = SSM.load(r / "ssm" / "ssm.npz")
    cohort = load_cohort_npz(r / "cohort" / "cohort.npz")
    targets = pd.read_csv(r / "patients" / "parameters.csv", dtype={"ID": str}).set_index("ID")
    settings = Settings(list(CORE_PARAMETERS), {}, 5, posture_deg=30.0)
    t0 = time.perf_counter()
    model = build_model(ssm, cohort.landmarks, settings)
    t_sur = time.perf_counter() - t0
    w = np.random.default_rng(0).uniform(-3, 3, (200, 5))
    x = np.c_[w, np.zeros(len(w))]
    t_sub = best_of(lambda: model.fn(x, list(CORE_PARAMETERS)))
    t_full = best_of(lambda: measure(ssm.sample(w), cohort.landmarks))
    print(
        f"measurement, 200 models: landmark subset {len(w) / t_sub:.0f} models/s, whole mesh "
        f"{len(w) / t_full:.0f} models/s, ratio {t_full / t_sub:.1f}"
    )
    print(f"surrogate ({settings.surrogate_samples} models): {t_sur:.2f} s")
    ids = cohort.ids[:n_patients]
    t0 = time.perf_counter()
    for pid in ids:
        model.fit({p: float(targets.at[pid, p]) for p in CORE_PARAMETERS})
    t_fit = time.perf_counter() - t0
    print(f"fit: {t_fit / len(ids):.2f} s per patient ({len(ids)} patients)")
    with np.load(r / "ssm" / "aligned.npz") as z:
        aligned = z["aligned"]
    t_proj = best_of(lambda: project_shapes(ssm, aligned, 5))
    print(f"projection: {t_proj:.3f} s for {len(aligned)} patients ({len(aligned) / t_proj:.0f} patients/s)")


if __name__ == "__main__":
    main(*(sys.argv[1:2] or ["results"]), *(int(a) for a in sys.argv[2:3]))
