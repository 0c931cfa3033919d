"""Throughput of spinecohort.measure.spinopelvic: models measured per second.

Batch of 1,000 models with the landmark-set sizes of a realistic mesh (~95k vertices per model): 35 endplate
patches of ~250 vertices (rims = their outer ring), two femoral-head caps of ~1,500 vertices, a 48-vertex
symphysis patch.  ``measure`` reads only landmark vertices, so the batch holds just those (~11.8k vertices
per model, remapped Landmarks); the other ~83k vertices of a real mesh are never touched and would cost only
the memory of the (B, N, 3) array.

Prints the batched throughput (best of 3 runs), the per-model loop throughput (measure called once per
model), their ratio, and the projected time for the 16,807-model virtual cohort.

Run: python benchmarks/bench_measure.py [n_models]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from spinecohort.cohort.landmarks import LEVELS, Landmarks
from spinecohort.measure.spinopelvic import measure


def unit(v):
    return v / np.linalg.norm(v)


def disk(centre, normal, radius=15.0, rings=9, per_ring=28):
    u = unit(np.array([0.0, 1.0, 0.0]) - normal[1] * normal)
    e2 = np.cross(normal, u)
    t = 2 * np.pi * np.arange(per_ring) / per_ring
    ring = np.cos(t)[:, None] * u + np.sin(t)[:, None] * e2
    rho = radius * np.arange(1, rings + 1) / rings
    pts = np.vstack([centre[None], (centre + rho[:, None, None] * ring[None]).reshape(-1, 3)])
    return pts, np.arange(len(pts) - per_ring, len(pts))  # 253 vertices, rim of 28


def cap(centre, radius, n=2000):
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    p = np.c_[np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z]
    return centre + radius * p[p[:, 2] > -0.5]  # ~1,500 vertices


def template() -> tuple[np.ndarray, Landmarks]:
    chunks, ep_sup, ep_inf, rim_sup, rim_inf = [], {}, {}, {}, {}

    def add(pts):
        start = sum(len(c) for c in chunks)
        chunks.append(pts)
        return np.arange(start, start + len(pts))

    c, n = np.array([0.0, -35.0, 105.0]), unit(np.array([0.0, np.tan(np.radians(35)), 1.0]))
    pts, rim = disk(c, n, 18.0)
    ep_sup["S1"] = add(pts)
    rim_sup["S1"] = ep_sup["S1"][rim]
    sag = np.interp(np.arange(34), [0, 23, 24, 33], [25.0, -19.0, -20.0, 28.0])
    for k in range(len(LEVELS) - 1, -1, -1):
        lv = LEVELS[k]
        n_inf = unit(np.array([0.0, np.tan(np.radians(sag[2 * k + 1])), 1.0]))
        n_sup = unit(np.array([0.0, np.tan(np.radians(sag[2 * k])), 1.0]))
        c_inf = c + 8.0 * unit(n + n_inf)
        c_sup = c_inf + 23.0 * unit(n_inf + n_sup)
        pts, rim = disk(c_inf, n_inf)
        ep_inf[lv] = add(pts)
        rim_inf[lv] = ep_inf[lv][rim]
        pts, rim = disk(c_sup, n_sup)
        ep_sup[lv] = add(pts)
        rim_sup[lv] = ep_sup[lv][rim]
        c, n = c_sup, n_sup
    fh = {"L": add(cap(np.array([-85.0, 0, 0]), 23.0)), "R": add(cap(np.array([85.0, 0, 0]), 23.0))}
    gx, gz = np.meshgrid(np.linspace(-5, 5, 6), np.linspace(-8, 8, 8))
    symph = add(np.c_[gx.ravel(), np.full(gx.size, 70.0), gz.ravel() - 40.0])
    pts = np.vstack(chunks)
    lm = Landmarks(
        part=np.zeros(len(pts), np.int16),
        part_names=("landmarks",),
        endplate_sup=ep_sup,
        endplate_inf=ep_inf,
        rim_sup=rim_sup,
        rim_inf=rim_inf,
        femoral_head=fh,
        body={lv: np.r_[ep_sup[lv], ep_inf[lv]] for lv in LEVELS},
        pubic_symphysis=symph,
    )
    return pts, lm


def main(n_models: int = 1000) -> None:
    pts, lm = template()
    rng = np.random.default_rng(0)
    # per-model axial rotation, translation and 0.3 mm vertex noise so no two models are identical
    a = rng.uniform(-0.3, 0.3, n_models)
    rot = np.zeros((n_models, 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = np.cos(a)
    rot[:, 0, 1], rot[:, 1, 0], rot[:, 2, 2] = -np.sin(a), np.sin(a), 1.0
    batch = np.einsum("bij,nj->bni", rot, pts) + rng.normal(0, 5, (n_models, 1, 3))
    batch += rng.normal(0, 0.3, batch.shape)
    print(f"batch: {n_models} models x {pts.shape[0]} landmark vertices ({batch.nbytes / 1e6:.0f} MB float64)")

    measure(batch[:10], lm)  # warm-up
    t_batch = np.inf
    for _ in range(3):  # best of 3: the machine is shared, the minimum is the least disturbed run
        t0 = time.perf_counter()
        df = measure(batch, lm, age=65.0)
        t_batch = min(t_batch, time.perf_counter() - t0)
    n_loop = min(100, n_models)
    t0 = time.perf_counter()
    for k in range(n_loop):
        measure(batch[k], lm, age=65.0)
    t_loop = (time.perf_counter() - t0) / n_loop

    rate = n_models / t_batch
    print(f"batched : {rate:10.0f} models/s  ({t_batch:.2f} s for {n_models})")
    print(f"looped  : {1 / t_loop:10.0f} models/s  (measure() per model, {n_loop} models)")
    print(f"ratio batched/looped: {rate * t_loop:.1f}x")
    print(f"projected 16,807-model virtual cohort: {16807 / rate:.1f} s")
    print(
        f"sanity: PI {df.PI.mean():.2f} +- {df.PI.std():.2f} deg, "
        f"max PI_identity_err {df.PI_identity_err.max():.1e} deg, {df.shape[1]} columns"
    )


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1000)
