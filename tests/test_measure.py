"""Tests of spinecohort.measure.spinopelvic on hand-built landmark geometry with closed-form answers.

The geometry is built here, independently of any generator, in the construction frame V = +z, A = +y,
Lh = +x (hip axis at the origin, left femoral head at -x).  Every endplate is a planar, centrally symmetric
disk with normal normalize(tan(cor), tan(sag), 1), whose sagittal inclination atan2(n_y, n_z) is exactly
``sag`` and coronal inclination atan2(n_x, n_z) exactly ``cor``; so every angle parameter is a sum/difference of
the prescribed tilts, and every positional parameter an angle of prescribed positions.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from spinecohort.cohort.landmarks import DISCS, LEVELS, MEASURED_SETS, Landmarks, disc_name
from spinecohort.measure.fits import _least_eigenpairs_nb, fit_planes, fit_spheres, plane_fits
from spinecohort.measure.formulas import cobb_angle
from spinecohort.measure.spinopelvic import UNITS, measure, measure_batch, parameter_table_header

NL = len(LEVELS)
LI = {lv: i for i, lv in enumerate(LEVELS)}
S1_RADIUS = 18.0
EP_RADIUS = 15.0


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def tilt_normal(sag_deg, cor_deg):
    return unit([np.tan(np.radians(cor_deg)), np.tan(np.radians(sag_deg)), 1.0])


def disk(centre, normal, radius, rings=5, per_ring=24):
    """Centrally symmetric planar disk; ring angle 0 lies along the in-plane anterior direction."""
    u = unit(np.array([0.0, 1.0, 0.0]) - normal[1] * normal)
    e2 = np.cross(normal, u)
    t = 2 * np.pi * np.arange(per_ring) / per_ring
    ring = np.cos(t)[:, None] * u + np.sin(t)[:, None] * e2
    rho = radius * np.arange(1, rings + 1) / rings
    pts = np.vstack([centre[None], (centre + rho[:, None, None] * ring[None]).reshape(-1, 3)])
    return pts, np.arange(len(pts) - per_ring, len(pts))


def sphere_cap(centre, radius, n=800):
    """Fibonacci points of a sphere, upper cap z > -0.3 r only (a head covered below by the neck)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    p = np.c_[np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z]
    return centre + radius * p[p[:, 2] > -0.3]


# Sagittal endplate tilt profile over the 34 endplate positions (T1 sup = 0, T1 inf = 1, ..., L5 inf = 33).
SAG_KNOTS = ([0, 23, 24, 33], [25.0, -19.0, -20.0, 28.0])
# Double coronal curve: upper T1-T4 (35 deg), main T5-L1 (50 deg, apex T9, convex right), lower L2-L5 (20 deg).
COR_KNOTS = ([0, 7, 8, 25, 26, 33], [10.0, -25.0, -25.0, 25.0, 25.0, 5.0])


def profile(knots):
    p = np.interp(np.arange(2 * NL), *knots)
    return p[0::2], p[1::2]  # superior, inferior


def build(
    pi=55.0,
    pt=20.0,
    sag=None,
    cor=None,
    pelvic_radius=110.0,
    hip_width=170.0,
    fh_radii=(23.0, 24.0),
    disc_h=None,
    body_h=None,
):
    """One model: (N, 3) points, Landmarks, and the construction quantities the tests compare against."""
    sag_sup, sag_inf = sag if sag is not None else profile(SAG_KNOTS)
    cor_sup, cor_inf = cor if cor is not None else profile(COR_KNOTS)
    disc_h = np.linspace(5.0, 11.0, NL) if disc_h is None else disc_h
    body_h = np.linspace(18.0, 27.0, NL) if body_h is None else body_h
    ss = pi - pt
    chunks, sets = [], {}

    def add(name, pts):
        start = sum(len(c) for c in chunks)
        chunks.append(pts)
        sets[name] = np.arange(start, start + len(pts))
        return start

    s1c = pelvic_radius * np.array([0.0, -np.sin(np.radians(pt)), np.cos(np.radians(pt))])
    s1n = tilt_normal(ss, 0.0)
    pts, rim = disk(s1c, s1n, S1_RADIUS)
    start = add("S1_sup", pts)
    sets["S1_rim"] = start + rim
    geo = {
        "S1c": s1c,
        "SS": ss,
        "sag_sup": sag_sup,
        "sag_inf": sag_inf,
        "cor_sup": cor_sup,
        "cor_inf": cor_inf,
        "disc_h": disc_h,
        "c_sup": {},
        "c_inf": {},
    }
    c_prev, n_prev = s1c, s1n
    for k in range(NL - 1, -1, -1):
        lv = LEVELS[k]
        n_inf = tilt_normal(sag_inf[k], cor_inf[k])
        n_sup = tilt_normal(sag_sup[k], cor_sup[k])
        c_inf = c_prev + disc_h[k] * unit(n_prev + n_inf)
        c_sup = c_inf + body_h[k] * unit(n_inf + n_sup)
        for side, c, n in (("inf", c_inf, n_inf), ("sup", c_sup, n_sup)):
            pts, rim = disk(c, n, EP_RADIUS)
            start = add(f"{lv}_{side}", pts)
            sets[f"{lv}_{side}_rim"] = start + rim
            geo[f"c_{side}"][lv] = c
        c_prev, n_prev = c_sup, n_sup
    add("FH_L", sphere_cap(np.array([-hip_width / 2, 0, 0]), fh_radii[0]))
    add("FH_R", sphere_cap(np.array([hip_width / 2, 0, 0]), fh_radii[1]))
    gx, gz = np.meshgrid(np.linspace(-5, 5, 4), np.linspace(-8, 8, 5))
    add("symph", np.c_[gx.ravel(), np.full(gx.size, 70.0), gz.ravel() - 40.0])
    points = np.vstack(chunks)
    lm = Landmarks(
        part=np.zeros(len(points), np.int16),
        part_names=("all",),
        endplate_sup={**{lv: sets[f"{lv}_sup"] for lv in LEVELS}, "S1": sets["S1_sup"]},
        endplate_inf={lv: sets[f"{lv}_inf"] for lv in LEVELS},
        rim_sup={**{lv: sets[f"{lv}_sup_rim"] for lv in LEVELS}, "S1": sets["S1_rim"]},
        rim_inf={lv: sets[f"{lv}_inf_rim"] for lv in LEVELS},
        femoral_head={"L": sets["FH_L"], "R": sets["FH_R"]},
        body={lv: np.r_[sets[f"{lv}_sup"], sets[f"{lv}_inf"]] for lv in LEVELS},
        pubic_symphysis=sets["symph"],
    )
    geo["body"] = {lv: 0.5 * (geo["c_sup"][lv] + geo["c_inf"][lv]) for lv in LEVELS}
    return points, lm, geo


def sag2d(v):
    return np.degrees(np.arctan2(v[1], v[2]))


def angle2d(u, w):
    """Unsigned angle between the sagittal (y, z) projections, by arccos (independent of atan2 sag)."""
    u, w = unit([u[1], u[2]]), unit([w[1], w[2]])
    return np.degrees(np.arccos(np.clip(u @ w, -1, 1)))


@pytest.fixture(scope="module")
def model():
    pts, lm, geo = build()
    return pts, lm, geo, measure(pts, lm, age=70.0).iloc[0]


def test_pelvic_parameters_closed_form(model):
    _, _, geo, r = model
    # imposed PI 55, PT 20, so SS = 35; the identity holds by construction of signed angles
    assert r.PT == pytest.approx(20.0, abs=1e-6)
    assert r.SS == pytest.approx(35.0, abs=1e-6)
    assert r.PI == pytest.approx(55.0, abs=1e-6)
    assert abs(r.PI - (r.PT + r.SS)) < 1e-6
    assert r.PI_identity_err < 1e-6
    assert r.endplate_rms_max < 1e-4  # exactly planar disks; raw-moment round-off floor is ~1e-5 mm
    # femoral heads: radii 23 (left) / 24 (right), centres 170 mm apart
    assert r.FH_radius_L == pytest.approx(23.0, abs=1e-6)
    assert r.FH_radius_R == pytest.approx(24.0, abs=1e-6)
    assert r.HA_width == pytest.approx(170.0, abs=1e-6)


def test_negative_pelvic_tilt():
    # anteverted pelvis: PT = -5, PI = 45 -> SS = 50; unsigned arccos angles would break PI = PT + SS here
    pts, lm, _ = build(pi=45.0, pt=-5.0)
    r = measure(pts, lm).iloc[0]
    assert r.PT == pytest.approx(-5.0, abs=1e-6)
    assert r.SS == pytest.approx(50.0, abs=1e-6)
    assert r.PI == pytest.approx(45.0, abs=1e-6)
    assert abs(r.PI - r.PT - r.SS) < 1e-6 and r.PI_identity_err < 1e-6


def test_sagittal_curvatures_closed_form(model):
    _, _, geo, r = model
    ss, s, i = geo["SS"], geo["sag_sup"], geo["sag_inf"]
    # LL = 35 - theta(L1 sup) = 35 - (-20) = 55; L4-S1 = 35 - theta(L4 sup); TK = theta(Ta sup) - theta(T12 inf)
    assert r.LL == pytest.approx(55.0, abs=1e-6)
    assert r.LL_L4S1 == pytest.approx(ss - s[LI["L4"]], abs=1e-6)
    assert r.LL_L1L5 == pytest.approx(i[LI["L5"]] - s[LI["L1"]], abs=1e-6)
    assert r.TK_T1T12 == pytest.approx(25.0 - (-19.0), abs=1e-6)
    assert r.TK_T4T12 == pytest.approx(s[LI["T4"]] - i[LI["T12"]], abs=1e-6)
    assert r.TK_T5T12 == pytest.approx(s[LI["T5"]] - i[LI["T12"]], abs=1e-6)
    assert r.PI_minus_LL == pytest.approx(0.0, abs=1e-6) and r.LL_minus_PI == pytest.approx(0.0, abs=1e-6)
    assert r.LDI == pytest.approx(100 * (ss - s[LI["L4"]]) / 55.0, abs=1e-6)
    assert not r.LDI_undefined


def test_global_parameters_vs_three_point_angles(model):
    _, _, geo, r = model
    ha, s1, t1, t2 = np.zeros(3), geo["S1c"], geo["body"]["T1"], geo["body"]["T2"]
    c7 = 2 * t1 - t2
    # T1SPI: the hip axis is at the origin, so it is the inclination of the T1 body centre itself
    assert r.T1SPI == pytest.approx(sag2d(t1), abs=1e-6)
    # TPA = angle T1c-HA-S1mid, GT = angle between HA->S1mid and S1mid->C7 (both vertices by arccos)
    assert r.TPA == pytest.approx(angle2d(t1 - ha, s1 - ha), abs=1e-6)
    assert r.TPA == pytest.approx(r.PT + r.T1SPI, abs=1e-9)
    assert r.GT == pytest.approx(angle2d(s1 - ha, c7 - s1), abs=1e-6)
    assert r.GT_T1 == pytest.approx(angle2d(s1 - ha, t1 - s1), abs=1e-6)
    assert r.GT_proxy == "extrapolated"
    # SVA proxies: posterosuperior S1 corner = centre - 18 mm along the plate's in-plane anterior direction
    s1ps_y = s1[1] - S1_RADIUS * np.cos(np.radians(geo["SS"]))
    assert r.SVA_T1 == pytest.approx(t1[1] - s1ps_y, abs=1e-6)
    assert r.SVA_C7est == pytest.approx(c7[1] - s1ps_y, abs=1e-6)


def test_t1_c7_proxy_option(model):
    pts, lm, _, r = model
    r2 = measure(pts, lm, c7_proxy="T1").iloc[0]
    assert r2.GT == pytest.approx(r.GT_T1, abs=1e-12) and r2.GT_proxy == "T1"


def test_disc_heights_closed_form(model):
    _, _, geo, r = model
    # central height = imposed spacing along the bisector normal; for coronally flat plates the anterior /
    # posterior rim heights are h -/+ 2 rho sin(delta/2), delta = theta(upper inf) - theta(lower sup)
    for k, (up, lo) in enumerate(DISCS):
        name = disc_name(up, lo)
        assert r[f"DH_{name}"] == pytest.approx(geo["disc_h"][k], abs=1e-6), name
    flat = profile(SAG_KNOTS), (np.zeros(NL), np.zeros(NL))
    pts, lm, g = build(sag=flat[0], cor=flat[1])
    rf = measure(pts, lm).iloc[0]
    for k, (up, lo) in enumerate(DISCS):
        name = disc_name(up, lo)
        lower_sup = g["SS"] if lo == "S1" else g["sag_sup"][LI[lo]]
        delta = np.radians(g["sag_inf"][LI[up]] - lower_sup)
        # S1 plate has radius 18, the L5 inferior one 15: rim heights use each plate's own radius
        r_up, r_lo = EP_RADIUS, (S1_RADIUS if lo == "S1" else EP_RADIUS)
        h = g["disc_h"][k]
        ha = h - (r_up + r_lo) * np.sin(delta / 2)
        hp = h + (r_up + r_lo) * np.sin(delta / 2)
        assert rf[f"DHa_{name}"] == pytest.approx(ha, abs=1e-6), name
        assert rf[f"DHp_{name}"] == pytest.approx(hp, abs=1e-6), name
    # the lordotic L5-S1 disc (theta L5 inf 28 < SS 35) is taller anteriorly
    assert rf["DHa_L5-S1"] > rf["DHp_L5-S1"]


def test_double_curve_cobb(model):
    _, _, _, r = model
    # main curve T5 sup (-25) to L1 inf (+25): 50 deg, apex where the tilt crosses 0 (T9), convex right
    assert r.Cobb == pytest.approx(50.0, abs=1e-6)
    assert (r.Cobb_upper, r.Cobb_lower, r.Cobb_apex) == ("T5", "L1", "T9")
    assert r.Cobb_convexity == 1
    # secondary: cranial T1 sup (+10) to T4 inf (-25) = 35 beats caudal L2 sup (25) to L5 inf (5) = 20
    assert r.Cobb2 == pytest.approx(35.0, abs=1e-6)
    assert (r.Cobb2_upper, r.Cobb2_lower) == ("T1", "T4")


def test_cobb_function_secondary_threshold():
    # single curve (tilts -8 ... +8 deg): main 16 deg, no secondary >= 10 -> NaN; mirrored -> convexity -1
    phi = np.linspace(-8, 8, 2 * NL)
    out = cobb_angle(phi[None, 0::2], phi[None, 1::2])
    assert out["cobb"][0] == pytest.approx(16.0) and np.isnan(out["cobb2"][0]) and out["upper2"][0] == -1
    assert (out["upper"][0], out["lower"][0], out["convexity"][0]) == (0, NL - 1, 1)
    out = cobb_angle(-phi[None, 0::2], -phi[None, 1::2])
    assert out["convexity"][0] == -1


def test_invariance_rotation_translation_label_swap(model):
    pts, lm, _, r0 = model
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    moved = pts @ rot.T + np.array([31.0, -12.0, 250.0])
    swapped = Landmarks(**{**lm.__dict__, "femoral_head": {"L": lm.femoral_head["R"], "R": lm.femoral_head["L"]}})
    r1 = measure(moved, swapped, age=70.0).iloc[0]
    for c in r0.index:
        if isinstance(r0[c], str):
            assert r1[c] == r0[c], c
        elif not (isinstance(r0[c], float) and np.isnan(r0[c])):
            assert r1[c] == pytest.approx(r0[c], abs=1e-4 if c == "endplate_rms_max" else 1e-8), c


def test_vertex_noise_tolerance(model):
    # 0.3 mm Gaussian vertex noise: stated tolerance 0.5 deg on angles, 0.3 mm on central heights and
    # femoral-head geometry, 1.5 mm on rim heights (two single noisy rim vertices, about 3 sigma)
    pts, lm, _, r0 = model
    noisy = pts + np.random.default_rng(11).normal(0, 0.3, pts.shape)
    r = measure(noisy, lm, age=70.0).iloc[0]
    for c in ("PI", "PT", "SS", "LL", "LL_L4S1", "TK_T4T12", "TPA", "GT", "Cobb"):
        assert abs(r[c] - r0[c]) < 0.5, c
    for _k, (up, lo) in enumerate(DISCS):
        name = disc_name(up, lo)
        assert abs(r[f"DH_{name}"] - r0[f"DH_{name}"]) < 0.3, name
        assert abs(r[f"DHa_{name}"] - r0[f"DHa_{name}"]) < 1.5, name
    for c in ("FH_radius_L", "FH_radius_R", "HA_width", "SVA_T1"):
        assert abs(r[c] - r0[c]) < 0.3 + (1.0 if c == "SVA_T1" else 0.0), c
    assert r.PI_identity_err < 1e-6  # the identity is exact for any plane, noisy or not
    assert 0.2 < r.endplate_rms_max < 0.45  # residual of 0.3 mm noise on ~145-vertex patches


def test_flat_lumbar_spine_ldi_undefined():
    # every lumbar superior endplate at the S1 slope (35 deg) -> LL = 0 -> LDI NaN, flagged, 0 points
    sup, inf = profile(SAG_KNOTS)
    sup, inf = sup.copy(), inf.copy()
    sup[LI["L1"] :], inf[LI["L1"] :] = 35.0, 35.0
    pts, lm, _ = build(sag=(sup, inf))
    r = measure(pts, lm).iloc[0]
    assert r.LL == pytest.approx(0.0, abs=1e-6)
    assert np.isnan(r.LDI) and bool(r.LDI_undefined) and r.LDI_pts == 0.0


def test_gap_columns_age_handling(model):
    pts, lm, _, r = model
    # PI 55, SS 35 -> RPV = 35 - 41.45 = -6.45 (0); LL 55 -> RLL = 55 - 63.1 = -8.1 (0)
    assert r.RPV == pytest.approx(-6.45, abs=1e-6) and r.RPV_pts == 0
    assert r.RLL == pytest.approx(-8.1, abs=1e-6) and r.RLL_pts == 0
    assert r.RSA == pytest.approx(r.GT - (0.48 * 55 - 15), abs=1e-9)
    assert r.GAP == r.GAP_noage + 1  # age 70 >= 60
    none = measure(pts, lm).iloc[0]
    assert np.isnan(none.GAP) and none.GAP_assumed_age == none.GAP_noage + 1  # assumed 65
    young = measure(pts, lm, assumed_age=40.0).iloc[0]
    assert young.GAP_assumed_age == young.GAP_noage and young.Age_pts == 0


def test_batch_equals_single():
    models = [build(pi=p, pt=t) for p, t in ((55, 20), (45, -5), (70, 32))]
    batch = np.stack([m[0] for m in models])
    lm = models[0][1]
    df = measure(batch, lm, age=[50, 65, 80])
    assert len(df) == 3
    for k, (pts, _, _) in enumerate(models):
        single = measure(pts, lm, age=[50, 65, 80][k])
        pd.testing.assert_frame_equal(df.iloc[[k]].reset_index(drop=True), single, atol=1e-9, rtol=0)
    assert df.PT.tolist() == pytest.approx([20, -5, 32], abs=1e-6)


def test_measuring_only_the_landmark_rows_gives_the_same_parameters_bit_for_bit(model):
    """``Landmarks.measured``: the shard pass measures the hex model on its landmark rows (no copy of its skin);
    the parameters are those of the whole model, to the bit, and the rows are the sets' vertices only."""
    pts, lm, _, _ = model
    # 50 vertices no set uses in front of the model's (every index moves), a body set on them
    junk = np.random.default_rng(4).normal(0.0, 100.0, (50, 3))
    pts = np.vstack([junk, pts])

    lm = dataclasses.replace(
        lm,
        part=np.concatenate([np.zeros(50, np.int16), lm.part]),
        body={"T1": np.arange(50)},
        pubic_symphysis=lm.pubic_symphysis + 50,
        **{name: {k: v + 50 for k, v in getattr(lm, name).items()} for name in MEASURED_SETS},
    )
    batch = np.stack([pts, pts + [3.0, -2.0, 1.0], 1.01 * pts])
    rows, on_rows = lm.measured()
    assert rows.tolist() == list(range(50, len(pts))) and on_rows.body == {}
    whole, landmark_rows = measure(batch, lm), measure(batch[:, rows], on_rows)
    pd.testing.assert_frame_equal(whole, landmark_rows, check_exact=True)


def test_batched_plane_fits_are_exact_far_from_the_origin():
    """The shard pass's plane fits (all patches of all models in one pass) on patches 0.5 m from the model's
    origin vertex: square corners (+-10, +-10) mm at z = +-h sign(xy) have a TLS plane z = 0 and out-of-plane RMS
    exactly h.  h = 1e-5 mm is the flatness of the synthetic endplates; raw moments about the far origin
    would lose it to cancellation (~1e-5 mm error), moments about each patch's first vertex keep it to 1e-9."""
    h = np.array([1e-5, 1.0])
    square = np.array([[10, 10, 1], [-10, -10, 1], [10, -10, -1], [-10, 10, -1.0]])
    far, near = square * [1, 1, h[0]] + [150.0, -80.0, 480.0], square * [1, 1, h[1]] + [-40.0, 20.0, 60.0]
    batch = np.repeat(np.concatenate([[[0.0, 0.0, 0.0]], far, near])[None], 2, axis=0)
    batch[1] += [1000.0, 2000.0, -3000.0]  # translation: the same planes
    centre, normal, rms = plane_fits(batch, {"far": np.arange(1, 5), "near": np.arange(5, 9)}, 0, np.array([0, 0, 1.0]))
    assert np.allclose(rms, h[None], rtol=1e-4, atol=1e-9)
    assert np.allclose(normal, [0, 0, 1], atol=1e-12)
    assert np.allclose(centre[:, 0], [150.0, -80.0, 480.0], atol=1e-9)  # relative to the origin vertex (row 0)


def test_least_eigenpairs_equal_lapack_on_flat_and_round_patches():
    """The plane fits' Jacobi eigensolver against LAPACK (``np.linalg.eigh``): covariances of flat patches
    (out-of-plane variance 1e-12..1e-2 mm^2 under two in-plane ones of 10-100 mm^2 that are equal to 1e-14
    relative: round endplates) and random SPD matrices.  The smallest eigenvalue agrees to round-off of the
    largest (both solvers are backward stable: <= ~1e-15 x |A|), the eigenvector to 1e-14 (up to sign), and
    A v = w v holds to 1e-15 x |A|."""
    rng = np.random.default_rng(7)
    n = 20000
    rot, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    in_plane = rng.uniform(10.0, 100.0, n)
    lam = np.stack([10 ** rng.uniform(-12, -2, n), in_plane, in_plane * (1 + 10 ** rng.uniform(-14, -1, n))], 1)
    flat = np.einsum("mij,mj,mkj->mik", rot, lam, rot)
    x = rng.normal(size=(n, 3, 3))
    for a in ((flat + flat.transpose(0, 2, 1)) / 2, x @ x.transpose(0, 2, 1)):
        w0, v0 = np.empty(n), np.empty((n, 3))
        _least_eigenpairs_nb(a, w0, v0)
        w, v = np.linalg.eigh(a)
        scale = np.abs(w).max(axis=1)
        assert (np.abs(w0 - w[:, 0]) / scale).max() < 1e-14
        assert (1 - np.abs(np.einsum("mi,mi->m", v0, v[:, :, 0]))).max() < 1e-14
        assert (np.linalg.norm(np.einsum("mij,mj->mi", a, v0) - w0[:, None] * v0, axis=1) / scale).max() < 1e-15
        assert np.abs(np.linalg.norm(v0, axis=1) - 1).max() < 1e-15
    # diagonal matrices: no rotation at all, the smallest diagonal entry and its axis exactly
    d = np.zeros((3, 3, 3))
    d[:, [0, 1, 2], [0, 1, 2]] = [[3.0, 1.0, 2.0], [1.0, 2.0, 0.5], [2.0, 3.0, 1.0]]
    w0, v0 = np.empty(3), np.empty((3, 3))
    _least_eigenpairs_nb(d, w0, v0)
    assert w0.tolist() == [1.0, 0.5, 1.0] and v0.tolist() == [[0, 1, 0], [0, 0, 1], [0, 0, 1]]


def test_fits_on_known_shapes():
    # partial sphere cap of radius 23 around (5, -7, 11): algebraic fit is exact without noise
    c, rad = fit_spheres(sphere_cap(np.array([5.0, -7.0, 11.0]), 23.0)[None])
    assert np.allclose(c[0], [5, -7, 11], atol=1e-9) and rad[0] == pytest.approx(23.0, abs=1e-9)
    # square corners (+-10, +-10) at z = sign(xy) mm: z is uncorrelated with x, y, so the TLS plane is z = 0
    # with residual RMS exactly 1 mm; the normal is oriented along the given vertical (-z here)
    p = np.array([[10, 10, 1], [-10, -10, 1], [10, -10, -1], [-10, 10, -1.0]])
    centre, normal, rms = fit_planes(p[None], np.array([0, 0, -1.0]))
    assert np.allclose(centre[0], 0) and np.allclose(normal[0], [0, 0, -1]) and rms[0] == pytest.approx(1.0)


def test_units_and_headers(model):
    pts, lm, _, _ = model
    df = measure(pts, lm)
    numeric = [c for c in df.columns if df[c].dtype.kind == "f" and c not in ("Cobb_convexity",)]
    assert not [c for c in numeric if c not in UNITS]
    h = parameter_table_header(df)
    assert "PI [deg]" in h.columns and "DH_L4-L5 [mm]" in h.columns and "LDI [%]" in h.columns
    assert "Cobb_upper" in h.columns


def test_bad_input_raises(model):
    pts, lm, _, _ = model
    with pytest.raises(ValueError, match="shape"):
        measure(pts[:, :2], lm)
    with pytest.raises(ValueError, match="vertical"):
        measure(pts, lm, vertical=(0, 0, 0))
    with pytest.raises(ValueError, match="c7_proxy"):
        measure(pts, lm, c7_proxy="C6")
    with pytest.raises(ValueError, match="age"):
        measure(np.stack([pts, pts]), lm, age=[60, 70, 80])
    with pytest.raises(ValueError, match="vertices"):
        measure(pts[:-5], lm)
    bad = pts.copy()
    bad[lm.femoral_head["L"][0]] = np.nan
    with pytest.raises(ValueError, match="femoral head"):
        measure(bad, lm)
    # an endplate vertex (the plane fits read the batch directly) and the origin vertex (every set is relative
    # to it) are named as well
    for level, side, where in (("L3", "inf", 7), ("T1", "sup", 0)):
        bad = np.stack([pts, pts])
        bad[1, getattr(lm, f"endplate_{side}")[level][where]] = np.inf
        with pytest.raises(ValueError, match=f"non-finite coordinates in landmark set {level} {side}$"):
            measure(bad, lm)


def test_float32_input(model):
    # float32 coordinates (~1e-5 mm resolution at 100 mm) change angles by far less than 1e-3 deg
    pts, lm, _, r0 = model
    r = measure(pts.astype(np.float32), lm, age=70.0).iloc[0]
    for c in ("PI", "PT", "LL", "TPA", "GT", "Cobb"):
        assert abs(r[c] - r0[c]) < 1e-3, c


def test_measure_batch_reads_landmark_file(model, tmp_path):
    # same result whether the landmarks come as an object or as the JSON file the workflow passes
    pts, lm, _, r0 = model
    lm.save(tmp_path / "lm.json")
    r = measure_batch(pts[None], tmp_path / "lm.json", vertical_axis=(0, 0, 2.0), age=70.0).iloc[0]
    assert r.PI == pytest.approx(r0.PI, abs=1e-12) and r.GAP == r0.GAP
