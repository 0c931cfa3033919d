"""Benchmark spinecohort.mesh.registration: speed, correspondence error against the truth, one patient's time.

Run: python benchmarks/bench_registration.py [speed|correspondence|patient]   (all three without argument)

* speed (2-4 minutes on 2 cores): BCPD time/iterations/final distance at 2k, 10k, 30k surface points.
* correspondence (~1 minute): the synthetic reference's L3 onto a deformed (five 2-5 mm bumps), rotated
  (10 deg), shifted and re-triangulated copy (spinecohort.testing.deformed_bone_case): correspondence error
  mean / 95th / max against the known truth for the rigid fit, BCPD with gamma 2 and 1, narrower kernels,
  two layers, and pycpd's deformable CPD (if installed: pip install pycpd; not a project dependency) at
  the same normalisation.
* real PATH: the same comparison on a real bone read from PATH in metres, e.g. the Visible Human L3 of
  Remus et al. 2021 (github.com/RemusR9/artisynth_lumbosacralSpineModel, file hybrid_LSS_model/src/artisynth/
  models/passiveComponents_PlosOne/geometry/RB/L3_Schrumpfverpacken.obj; not vendored here).
* patient [synthetic|real [SIGMA_START_MM]] (~25 s per coarse synthetic patient of one core, ~100 s per real one;
  run with OMP_NUM_THREADS=1): spinecohort.cohort.register with that reference (`register.reference`) on three
  patients of its generator brought per bone (re-triangulated, shuffled), the first BCPD layer from BCPD's gamma
  or from SIGMA_START_MM (`register.bone.sigma_start_mm`): CPU seconds of the placement and of the bones, surface
  distances, correspondence error (worst bone), PI/PT/SS/LL error against the generator.

Speed section:
Case: a vertebral-body-sized superellipsoid (40 x 30 x 24 mm) as source; the target is the same shape
sampled differently and moved by a smooth Gaussian RBF field (10 mm wide, ~1.5 mm mean).  Both sets are
voxel-downsampled (BCPD++) before registration; the field is then applied to every source point.
"""

import sys
import time

import numpy as np

from spinecohort.cohort.surfaces import superellipsoid
from spinecohort.mesh import registration as reg


def body(n_points):
    # superellipsoid gives n_theta * n_rings + 2 vertices; keep n_theta ~ 1.6 n_rings
    n_rings = int(round(np.sqrt(n_points / 1.6)))
    return superellipsoid(np.zeros(3), np.eye(3), (20.0, 15.0, 12.0), 2 * int(round(0.8 * n_rings)), n_rings)


def field(p):
    centres = np.array([[8.0, -5, 3], [-10, 6, -4], [2, 9, 8], [-4, -8, -6]])
    amps = np.array([[1.5, -1.0, 2.0], [-2.0, 1.0, 0.5], [0.5, 2.0, -1.5], [1.0, -1.5, -1.0]])
    return np.exp(-((p[:, None] - centres[None]) ** 2).sum(-1) / (2 * 10.0**2)) @ amps


def speed():
    print("surface_distance (vtkImplicitPolyDataDistance, exact):")
    tv, tf = body(30_000)
    q = tv + np.random.default_rng(0).normal(0, 1.0, tv.shape)
    t0 = time.perf_counter()
    reg.surface_distance(q, tv, tf)
    dt = time.perf_counter() - t0
    print(f"  {len(q)} points vs {len(tf)} triangles: {dt:.2f} s  ({len(q) / dt:,.0f} points/s)")

    print("rigid CPD (similarity, 1000 sampled points) + ICP on all points:")
    src, _ = body(10_000)
    t0 = time.perf_counter()
    r = reg.rigid_register(src, 1.05 * src + [2.0, -1.0, 3.0])
    print(f"  10k points: {time.perf_counter() - t0:.2f} s, {r.iterations} iterations, rms {r.rms:.4f} mm")

    print("non-rigid BCPD (beta 2, lam 8, w 0.1, K 70, max_iter 200, tol 1e-4):")
    print(
        f"  {'points':>7} {'radius':>6} {'M_ds':>6} {'N_ds':>6} {'time s':>7} {'iters':>5} "
        f"{'start mm':>8} {'final mm':>8} {'pts/s':>8}"
    )
    for n, radius in ((2_000, 0.0), (10_000, 1.3), (30_000, 1.3)):
        src, _ = body(n)
        tv, tf = body(int(n * 1.3))
        target = tv + field(tv)
        m_ds = len(reg.voxel_downsample(src, radius))
        n_ds = len(reg.voxel_downsample(target, radius))
        start = np.mean(reg.surface_distance(src, target, tf))
        t0 = time.perf_counter()
        res = reg.nonrigid_register(src, target, tf, downsample_radius=radius, max_iter=200, tol=1e-4)
        dt = time.perf_counter() - t0
        print(
            f"  {len(src):>7} {radius:>6.1f} {m_ds:>6} {n_ds:>6} {dt:>7.1f} {res.iterations:>5} "
            f"{start:>8.3f} {res.mean_distance:>8.4f} {len(src) / dt:>8.0f}"
        )
    print("multilayer (bound 0.04 mm) on the 30k case:")
    t0 = time.perf_counter()
    res = reg.multilayer_register(src, target, tf, bound=0.04, downsample_radius=1.3, max_iter=200, tol=1e-4)
    print(
        f"  {time.perf_counter() - t0:.1f} s, {res.iterations} iterations, layers "
        + ", ".join(f"beta {h['beta']:g}: {h['mean_distance']:.4f} mm" for h in res.history)
    )
    print(
        "memory: correspondence blocks of <= 4e6 float64 (32 MB) plus the M_ds x K Nystrom basis; "
        "never an M x N or M x M matrix."
    )


def _errors(moved, truth):
    e = np.linalg.norm(moved - truth, axis=1)
    return f"{e.mean():6.3f} {np.percentile(e, 95):6.3f} {e.max():6.2f}"


def correspondence():
    for bone, seed in (("L3", 3), ("L3", 7), ("T8", 3), ("hip_left", 3)):
        _correspondence(bone, seed)


def real(path, unit_mm=1000.0):
    """A real bone from a file (e.g. the Visible Human L3 of Remus et al. 2021, in metres: see the module doc)."""
    from spinecohort.cohort.bones import read_mesh
    from spinecohort.testing import deformed_copy

    pts, faces = read_mesh(path)
    pts = pts * unit_mm
    _compare(f"{path} (seed 3)", pts, *deformed_copy(pts, faces, seed=3))


def _correspondence(bone, seed):
    from spinecohort.testing import deformed_bone_case

    src, _, truth, target, tf = deformed_bone_case(bone, seed=seed)
    _compare(f"{bone} (seed {seed})", src, truth, target, tf)


def _compare(name, src, truth, target, tf):
    print(f"{name}: {len(src)} source points, {len(target)} target points (re-triangulated, shuffled)")
    print(f"  {'method':44s} {'CPU s':>6} {'mean':>6} {'p95':>6} {'max':>6} {'surface mm':>10}")

    def row(name, fn):
        t0 = time.process_time()
        moved = fn()
        dt = time.process_time() - t0
        d = np.mean(reg.surface_distance(moved, target, tf))
        print(f"  {name:44s} {dt:6.1f} {_errors(moved, truth)} {d:10.3f}", flush=True)

    rigid = reg.rigid_register(src, target, scale=True)
    row(f"rigid CPD + ICP (scale {rigid.s:.3f})", lambda: rigid.transformed)
    start = rigid.transformed
    for kw in ({"gamma": 2.0}, {"gamma": 1.0}, {"gamma": 1.0, "beta": 1.0}, {"gamma": 1.0, "lam": 2.0}):
        row(f"BCPD {kw}", lambda kw=kw: reg.nonrigid_register(start, target, **kw).deformed)
    row(
        "2 layers, the second restarted from all pairs",
        lambda: (
            reg.nonrigid_register(
                reg.nonrigid_register(start, target, gamma=1.0).deformed, target, beta=1.0, gamma=2.0
            ).deformed
        ),
    )
    for layers in (2, 3):
        row(
            f"{layers} layers, each from the previous sigma",
            lambda layers=layers: (
                reg.multilayer_register(start, target, tf, bound=1e-9, max_layers=layers, gamma=1.0).deformed
            ),
        )
    try:
        from pycpd import DeformableRegistration
    except ImportError:
        print("  pycpd not installed: pip install pycpd for the peer's row")
        return
    centre = target.mean(0)
    unit = np.sqrt(np.mean(np.sum((target - centre) ** 2, 1)))

    def peer():
        cpd = DeformableRegistration(X=(target - centre) / unit, Y=(start - centre) / unit, alpha=2.0, beta=2.0, w=0.1)
        return cpd.register()[0] * unit + centre

    row("pycpd 2.0 deformable CPD (alpha 2, beta 2, w 0.1)", peer)


def patient(n=3, reference="synthetic", sigma_start_mm=None):
    from spinecohort.cohort.bones import BoneMesh, check_bone
    from spinecohort.cohort.register import DEFAULTS, real_reference, register_patient, synthetic_reference
    from spinecohort.cohort.user_folder import bone_meshes, retriangulate
    from spinecohort.measure.spinopelvic import measure

    if reference == "real":
        from spinecohort.cohort.real import generate_real_cohort

        ref, c = real_reference(), generate_real_cohort(n, seed=5)
    else:
        from spinecohort.cohort.synthetic import generate_cohort

        ref, c = synthetic_reference("coarse"), generate_cohort(n, seed=5, resolution="coarse")
    params = {"bone": {**DEFAULTS["bone"], "sigma_start_mm": sigma_start_mm}}
    rng = np.random.default_rng(0)
    print(
        f"{reference} reference: {len(ref.points)} vertices, 22 bones; first BCPD layer from "
        f"{'gamma' if sigma_start_mm is None else f'{sigma_start_mm:g} mm'}; patients re-triangulated per bone, shuffled"
    )
    for pid, pts in zip(c.ids, c.vertices):
        pieces = [
            check_bone(BoneMesh(name, *retriangulate(p, f, rng), name), pid, "mm")
            for name, (p, f) in bone_meshes(pts, c.faces, ref.bone).items()
        ]
        t0 = time.process_time()
        out, rep = register_patient(ref, pieces, pid, named=True, params=params)
        total = time.process_time() - t0
        m = measure(out[None], ref.landmarks).iloc[0]
        row = c.table.set_index("ID").loc[pid]
        err = ", ".join(f"{k} {m[k] - row[k]:+.2f}" for k in ("PI", "PT", "SS", "LL"))
        worst = np.linalg.norm(out - pts, axis=1)
        per_bone = {b: worst[ref.vertices_of(b)].mean() for b in rep.bone}
        bad = max(per_bone, key=per_bone.get)
        print(
            f"  {pid}: {total:.1f} s CPU (placement {rep.attrs['placement_cpu_s']:.1f} s, bones {rep.cpu_s.sum():.1f} s,"
            f" slowest {rep.loc[rep.cpu_s.idxmax(), 'bone']} {rep.cpu_s.max():.1f} s); surface distance mean "
            f"{rep.mean_mm.mean():.3f} mm (worst bone {rep.mean_mm.max():.3f}, back {rep.back_mean_mm.max():.3f}); "
            f"correspondence {_errors(out, pts)} mm (worst bone {bad} {per_bone[bad]:.2f}); error deg: {err}",
            flush=True,
        )


if __name__ == "__main__":
    if sys.argv[1:2] == ["real"]:
        real(sys.argv[2])
        sys.exit(0)
    if sys.argv[1:2] == ["patient"] and len(sys.argv) > 2:  # patient REFERENCE [SIGMA_START_MM]
        patient(reference=sys.argv[2], sigma_start_mm=float(sys.argv[3]) if len(sys.argv) > 3 else None)
        sys.exit(0)
    sections = {"speed": speed, "correspondence": correspondence, "patient": patient}
    for name in sys.argv[1:] or list(sections):
        sections[name]()
