"""Benchmark of spinecohort.mesh.quality / spinecohort.mesh.repair.

    python benchmarks/bench_quality.py            # 103 823 and 512 000 hexes
    python benchmarks/bench_quality.py 20         # one small mesh (quick run)

Meshes: structured n^3 hexes, nodes perturbed by U(+-0.22 h) plus 30 nodes kicked by N(0, h) (some inverted).
Prints elements checked per second for our numba / numpy kernels and vtkMeshQuality (ScaledJacobian, grid built
beforehand, not timed), their ratio, the full-metrics kernel, the Bernstein certificate, the fused morph+check,
and the repair time per deliberate-inversion case on a 20^3 graded bent block. Best of 3 repeats.
"""

import sys
import time

import numpy as np
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from spinecohort.mesh import repair as r
from spinecohort.mesh.quality.certificate import certify_valid
from spinecohort.mesh.quality.kernels import (
    bernstein_bounds_nb,
    full_metrics_batch_nb,
    full_metrics_nb,
    min_scaled_jacobian_nb,
    morph_scaled_jacobian_nb,
)
from spinecohort.mesh.quality.table3 import hex_quality_metrics, model_quality, part_codes
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.vtk_mesh import hexahedra
from spinecohort.testing import hex_grid_node_id, perturbed_cube_grid, unit_cube_grid


def grid(n):
    X, H = unit_cube_grid(n)
    return X, H, hex_grid_node_id((n, n, n))


def best_of(f, repeats=3):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = f()
        times.append(time.perf_counter() - t)
    return min(times), out


def vtk_filter(X, H):
    mq = vtk.vtkMeshQuality()
    mq.SetInputData(hexahedra(X, H))
    mq.SetHexQualityMeasureToScaledJacobian()
    return mq


def bench_check(n):
    X, H = perturbed_cube_grid(n)
    E = len(H)
    print(f"\n== {n}^3 mesh: {E} hexes, {len(X)} nodes ==")
    min_scaled_jacobian_nb(X[:8], H[:1] * 0)  # compile outside the timing
    mq = vtk_filter(X, H)

    def run_vtk():
        mq.Modified()
        mq.Update()
        return vtk_to_numpy(mq.GetOutput().GetCellData().GetArray("Quality"))

    t_vtk, sj_vtk = best_of(run_vtk)
    t_nb, sj_nb = best_of(lambda: min_scaled_jacobian_nb(X, H))
    t_np, sj_np = best_of(lambda: scaled_jacobian(X, H))
    print(
        f"agreement: max|numba - vtk| = {np.abs(sj_nb - sj_vtk).max():.1e}, "
        f"max|numpy - vtk| = {np.abs(sj_np - sj_vtk).max():.1e}, invalid {int((sj_nb <= 0).sum())} "
        f"(vtk {int((sj_vtk <= 0).sum())})"
    )
    print(f"vtkMeshQuality ScaledJacobian : {E / t_vtk / 1e6:6.2f} M elem/s  ({t_vtk * 1e3:7.1f} ms)")
    print(
        f"numba min_scaled_jacobian_nb  : {E / t_nb / 1e6:6.2f} M elem/s  ({t_nb * 1e3:7.1f} ms)  "
        f"ratio numba/vtk = {t_vtk / t_nb:.2f}x"
    )
    print(
        f"numpy scaled_jacobian (chunks): {E / t_np / 1e6:6.2f} M elem/s  ({t_np * 1e3:7.1f} ms)  "
        f"ratio numpy/vtk = {t_vtk / t_np:.2f}x"
    )
    t_full, _ = best_of(lambda: full_metrics_nb(X, H))
    print(f"numba full_metrics_nb (7 metrics): {E / t_full / 1e6:6.2f} M elem/s  ({t_full * 1e3:7.1f} ms)")
    P = np.ascontiguousarray(X[H])
    t_bern, _ = best_of(lambda: bernstein_bounds_nb(P))
    print(f"numba bernstein_bounds_nb (27 coefficients): {E / t_bern / 1e6:6.2f} M elem/s")
    t_cert, cert = best_of(lambda: certify_valid(X, H), repeats=1)
    print(
        f"certify_valid (all elements, incl. subdivision): {E / t_cert / 1e6:6.2f} M elem/s, "
        f"{int((cert < 0).sum())} not certified"
    )
    # the shard pass's check + Table 3 (vectorised across models) vs the per-element kernel of the same metrics
    rng = np.random.default_rng(2)
    batch = X + rng.normal(0, 0.01 / n, (56, *X.shape))
    part = np.array(["vertebra", "AF", "NP"])[rng.integers(0, 3, E)]
    codes = part_codes(part)
    model_quality(batch[:8], H, part, codes)
    t_mq, _ = best_of(lambda: model_quality(batch, H, part, codes))
    t_fm, _ = best_of(lambda: full_metrics_batch_nb(batch[:8], H))
    ns_mq, ns_fm = t_mq / (56 * E) * 1e9, t_fm / (8 * E) * 1e9
    print(
        f"model_quality (check + Table 3, 56 models across vector lanes): {ns_mq:.0f} ns per hex; "
        f"full_metrics_batch_nb (per element, 7 metrics): {ns_fm:.0f} ns per hex; ratio {ns_fm / ns_mq:.1f}x"
    )
    t_all, _ = best_of(lambda: hex_quality_metrics(X, H), repeats=1)
    print(f"hex_quality_metrics (full + certificate): {t_all:.2f} s per sample")
    rng = np.random.default_rng(1)
    B, n_modes = 4, 5
    modes = rng.normal(0, 0.03, (n_modes, len(X), 3))
    w = rng.uniform(-3, 3, (B, n_modes))
    t_fused, _ = best_of(lambda: morph_scaled_jacobian_nb(X, modes, w, H), repeats=2)
    print(
        f"numba fused morph ({n_modes} modes) + check, B={B}: {B * E / t_fused / 1e6:6.2f} M elem/s "
        f"({t_fused / B * 1e3:.1f} ms per sample)"
    )


def bench_repair():
    n = 20
    X0, H, nid = grid(n)
    g = np.cumsum(np.r_[0.0, 1.05 ** np.arange(n)])
    x = g[X0[:, 0].astype(int)] / g[-1] * n
    y = X0[:, 1] + 0.02 * x**2
    R = 16.0
    ref = np.stack([(R + x) * np.cos(X0[:, 2] / R) - R, y, (R + x) * np.sin(X0[:, 2] / R)], 1)
    print(f"\n== repair on a graded bent {n}^3 block ({len(H)} hexes, min sJ {scaled_jacobian(ref, H).min():.3f}) ==")

    def push(node, towards, f):
        X = ref.copy()
        X[node] += f * (ref[towards] - ref[node])
        return X

    c, s = ref[nid(10, 10, 10)], 2.0
    d = ref - c
    rng = np.random.default_rng(3)
    interior = np.setdiff1d(np.arange(len(ref)), r.boundary_nodes(H))
    kicks = ref.copy()
    sel = rng.choice(interior, 10, replace=False)
    kicks[sel] += rng.normal(0, 0.9, (10, 3))
    cases = {
        "interior node pushed 1.6 h": push(nid(10, 10, 10), nid(11, 10, 10), 1.6),
        "sub-surface node through surface": push(nid(10, 10, 1), nid(10, 10, 0), 1.6),
        **{
            f"localised shear mode w={w}": ref
            + np.c_[w * d[:, 2] / s * np.exp(-(d**2).sum(1) / (2 * s * s)), np.zeros((len(ref), 2))]
            for w in (6, 8)
        },
        "10 random interior kicks 0.9 h": kicks,
        "surface face folded in-plane 1.3 h": push(nid(10, 10, 0), nid(11, 10, 0), 1.3),
    }
    for name, X in cases.items():
        t = time.perf_counter()
        try:
            Y, rep = r.untangle(X, H, ref)
        except r.RepairError as e:
            print(f"{name:38s} FAILED: {e}")
            continue
        dt = time.perf_counter() - t
        cert_ok = bool(np.all(certify_valid(Y, H) == 1))
        print(
            f"{name:38s} invalid {rep.invalid_before:3d} -> {rep.invalid_after}, certified {cert_ok}, "
            f"moved {rep.n_nodes_moved:4d}, max|dx| {rep.max_displacement_mm:.2f} mm, min sJ "
            f"{rep.min_scaled_jacobian_before:+.3f} -> {rep.min_scaled_jacobian_after:.3f}, "
            f"sliding {rep.sliding}, {dt:.2f} s"
        )


def bench_repair_large(n=80):
    X0, H, nid = grid(n)
    t = time.perf_counter()
    ctx = r.prepare_untangle(H, X0)
    t_ctx = time.perf_counter() - t
    X = X0.copy()
    c = nid(n // 2, n // 2, n // 2)
    X[c] += 1.6 * (X0[nid(n // 2 + 1, n // 2, n // 2)] - X0[c])
    t = time.perf_counter()
    Y, rep = r.untangle(X, H, X0, context=ctx)
    t_rep = time.perf_counter() - t
    print(
        f"\n== repair on a {n}^3 block ({len(H)} hexes) ==\nprepare_untangle (once per cohort): {t_ctx:.2f} s; "
        f"interior push 1.6 h: invalid {rep.invalid_before} -> {rep.invalid_after}, {t_rep:.2f} s per sample "
        f"(whole-mesh check + certificate + local repair)"
    )


if __name__ == "__main__":
    sizes = [int(a) for a in sys.argv[1:]] or [47, 80]
    for n in sizes:
        bench_check(n)
    bench_repair()
    bench_repair_large(max(sizes))
