"""Benchmark: synthetic cohort generation, STL I/O and SSM building at a given resolution.

    python benchmarks/bench_ssm.py [--n 42] [--resolution default]

Prints wall times, throughputs and the SSM figures (modes for 95 %, generalization, specificity).
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from spinecohort.cohort.loading import load_cohort, write_cohort_folder
from spinecohort.cohort.synthetic import generate_cohort
from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.procrustes import procrustes_align
from spinecohort.ssm.quality import generalization, specificity


def timed(label, fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    dt = time.perf_counter() - t0
    print(f"{label:<34s} {dt:8.2f} s")
    return out, dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=42)
    ap.add_argument("--resolution", default="default")
    a = ap.parse_args()
    cohort, t_gen = timed("generate cohort", generate_cohort, a.n, resolution=a.resolution)
    p, n, _ = cohort.vertices.shape
    print(
        f"  {p} patients x {n} vertices ({len(cohort.faces)} triangles): {p / t_gen:.2f} patients/s, "
        f"{p * n / t_gen / 1e6:.2f} M vertices/s; {cohort.n_candidates} candidates drawn"
    )
    with tempfile.TemporaryDirectory() as d:
        _, t_w = timed(
            "write STL folder",
            write_cohort_folder,
            d,
            cohort.ids,
            cohort.vertices,
            cohort.faces,
            cohort.landmarks,
            cohort.table,
        )
        size = sum(f.stat().st_size for f in Path(d).glob("*.stl"))
        print(f"  {size / 1e6:.1f} MB of STL, {size / 1e6 / t_w:.1f} MB/s")
        loaded, t_r = timed(
            "read + validate cohort",
            load_cohort,
            sorted(Path(d).glob("*.stl")),
            Path(d) / "patients.csv",
            Path(d) / "landmarks.json",
        )
        print(f"  {size / 1e6 / t_r:.1f} MB/s")
    gpa, _ = timed("generalized Procrustes", procrustes_align, loaded.points)
    print(f"  {gpa.n_iterations} iterations, last mean change {gpa.mean_change_mm[-1]:.1e} mm")
    ssm, _ = timed("PCA (thin SVD)", build_ssm, gpa.aligned)
    print(
        f"  {ssm.n_modes} modes; 95 % variance with {ssm.modes_for_variance(0.95)} modes; "
        f"first 5 explain {np.round(100 * ssm.explained_variance_ratio[:5], 1)} %"
    )
    gen, _ = timed("generalization (LOO, all modes)", generalization, gpa.aligned)
    spec, _ = timed("specificity (1000 samples/mode)", specificity, ssm, gpa.aligned, 1000, 20)
    for m in (1, 3, 5, 10, 20):
        if m <= len(spec):
            print(
                f"  {m:2d} modes: generalization {gen['generalization_mm'][m - 1]:.2f} mm, "
                f"specificity {spec['specificity_mm'][m - 1]:.2f} mm"
            )
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
