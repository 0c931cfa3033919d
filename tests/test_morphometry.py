"""Vertebral morphometry (spinecohort.anatomy.morphometry): closed-form shapes and the real Visible Human
lumbar bodies of Remus et al. 2021 against Panjabi et al. 1992."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import pyvista as pv
from scipy.spatial.transform import Rotation

from spinecohort.anatomy import morphometry as M


def _tri(mesh: pv.PolyData) -> tuple[np.ndarray, np.ndarray]:
    mesh = mesh.triangulate().clean()
    return np.asarray(mesh.points, float), mesh.faces.reshape(-1, 4)[:, 1:].astype(np.int64)


def _box(lo, hi, level=30):
    return _tri(pv.Box(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]), level=level, quads=False))


def _plate(centre, d1, d2, size=6.0, n=7):
    """A flat square patch spanned by the unit directions d1, d2 (its vertices are one facet surface)."""
    u = np.linspace(-size / 2, size / 2, n)
    uu, vv = np.meshgrid(u, u, indexing="ij")
    pts = np.asarray(centre) + uu.reshape(-1, 1) * d1 + vv.reshape(-1, 1) * d2
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    return pts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _cone(base_centre, apex, radius, n=32):
    """Closed cone surface: a ring of ``n`` points around ``base_centre``, the apex and the base centre."""
    base_centre, apex = np.asarray(base_centre, float), np.asarray(apex, float)
    axis = (apex - base_centre) / np.linalg.norm(apex - base_centre)
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = base_centre + radius * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    pts = np.vstack([ring, apex, base_centre])
    i = np.arange(n)
    faces = np.concatenate(
        [np.stack([i, (i + 1) % n, np.full(n, n)], 1), np.stack([(i + 1) % n, i, np.full(n, n + 1)], 1)]
    )
    return pts, faces


def _trace_plane(t_deg, s_deg, right=False):
    """In-plane directions of a facet whose transverse trace makes t_deg with the mid-sagittal plane and whose
    sagittal trace makes s_deg with the transverse plane (frame: anterior, right, superior)."""
    t, s = np.radians(t_deg), np.radians(s_deg)
    return np.array([np.cos(t), -np.sin(t) if right else np.sin(t), 0.0]), np.array([np.cos(s), 0.0, np.sin(s)])


# The synthetic vertebra, in its own frame (anterior, right, superior), mm
W, D, H = 40.0, 30.0, 25.0  # body width, depth, height
PED_R, PED_Y, PED_SCALE = 4.0, 12.0, 1.5  # pedicle radius, lateral offset; the right one is 1.5x as high
LAM_A = -27.0  # inner (anterior) face of the lamina
APEX = np.array([-60.0, 0.0, -10.0])  # spinous tip, caudal like a thoracic process
FACETS = {"sup_left": (35.0, 70.0), "sup_right": (35.0, 70.0), "inf_left": (60.0, 50.0), "inf_right": (60.0, 50.0)}


def synthetic_vertebra():
    """(points, faces, parts, superior endplate, inferior endplate): box body, cylinder pedicles (the right one
    elliptic), box lamina, conical spinous process and flat facet plates of known orientation."""
    chunks, parts = [], {}

    def add(name, pts, faces):
        start = sum(len(c[0]) for c in chunks)
        chunks.append((pts, faces + start))
        parts[name] = np.arange(start, start + len(pts))

    add("body", *_box((-D / 2, -W / 2, -H / 2), (D / 2, W / 2, H / 2)))
    for side, y, scale in (("left", -PED_Y, 1.0), ("right", PED_Y, PED_SCALE)):
        cyl = pv.Cylinder(center=(-21.0, y, 0.0), direction=(1, 0, 0), radius=PED_R, height=12.0, resolution=64)
        pts, faces = _tri(cyl)
        pts[:, 2] *= scale
        add(f"pedicle_{side}", pts, faces)
    add("lamina", *_box((-33.0, -14.0, -6.0), (LAM_A, 14.0, 6.0), level=12))
    add("spinous", *_cone((-34.0, 0.0, 0.0), APEX, 3.0))
    for name, (t, s) in FACETS.items():
        right = name.endswith("right")
        centre = (-27.0, 12.0 if right else -12.0, 10.0 if name.startswith("sup") else -10.0)
        add(f"facet_{name}", *_plate(centre, *_trace_plane(t, s, right)))
    pts = np.vstack([c[0] for c in chunks])
    faces = np.vstack([c[1] for c in chunks])
    body = pts[parts["body"]]
    # built in frame coordinates (anterior, right, superior); in a right-handed world right = anterior x superior
    # is -y when anterior = x and superior = z, so the world points are these with y negated (faces flipped)
    pts = pts * [1.0, -1.0, 1.0]
    faces = faces[:, ::-1]
    sup = parts["body"][np.isclose(body[:, 2], H / 2)]
    inf = parts["body"][np.isclose(body[:, 2], -H / 2)]
    return pts, faces, parts, sup, inf


def _moved(pts, seed=3):
    """The same points after a random rotation and translation (measurements must not change)."""
    rot = Rotation.random(random_state=seed).as_matrix()
    return pts @ rot.T + np.array([120.0, -35.0, 410.0]), rot


def test_synthetic_vertebra_closed_form():
    pts, faces, parts, sup, inf = synthetic_vertebra()
    moved, _ = _moved(pts)
    m = M.measure_vertebra(moved, faces, parts, sup, inf)
    # body box: width 40, depth 30, height 25 on both endplates and both walls
    for k, want in (("endplate_width", W), ("endplate_depth", D)):
        for end in ("upper", "lower"):
            assert m[f"{k}_{end}"] == pytest.approx(want, abs=1e-6)
    assert m["body_height_anterior"] == pytest.approx(H, abs=1e-6)
    assert m["body_height_posterior"] == pytest.approx(H, abs=1e-6)
    # pedicles: circle of diameter 8 (left), ellipse 8 wide x 12 high (right); 64-gon: within 0.01 mm
    assert m["pedicle_width_left"] == pytest.approx(2 * PED_R, abs=0.01)
    assert m["pedicle_height_left"] == pytest.approx(2 * PED_R, abs=0.01)
    assert m["pedicle_width_right"] == pytest.approx(2 * PED_R, abs=0.01)
    assert m["pedicle_height_right"] == pytest.approx(2 * PED_R * PED_SCALE, abs=0.02)
    # canal: medial pedicle faces at y = +-(12 - 4) -> 16 wide; posterior wall a = -15 to the lamina at -27 -> 12
    assert m["canal_width"] == pytest.approx(2 * (PED_Y - PED_R), abs=0.01)
    assert m["canal_depth"] == pytest.approx(-D / 2 - LAM_A, abs=1e-6)
    # spinous length: the lamina's mid-line inner point (-27, 0, 0) to the apex: sqrt(33^2 + 10^2) = 34.48 mm
    assert m["spinous_length"] == pytest.approx(np.hypot(33.0, 10.0), abs=1e-6)
    # facets: the plates were spanned by their transverse and sagittal traces
    for which in ("sup", "inf"):
        t, s = FACETS[f"{which}_left"]
        for side in ("left", "right"):
            assert m[f"facet_{which}_transverse_{side}"] == pytest.approx(t, abs=1e-6)
            assert m[f"facet_{which}_sagittal_{side}"] == pytest.approx(s, abs=1e-6)


def test_parts_from_region_labels():
    """Region labels per vertex (names in label order) give the same parts as the vertex sets."""
    pts, faces, parts, sup, inf = synthetic_vertebra()
    names = ("sacrum",) + M.PARTS  # a label order with a non-vertebral region first
    region = np.zeros(len(pts), int)
    for name, idx in parts.items():
        region[idx] = names.index(name)
    other = np.zeros(len(pts), bool)
    other[parts["lamina"]] = True  # a vertebra mask that leaves the lamina to another level
    got = M.parts_of_vertebra(region, names, ~other)
    assert set(got) == set(parts) - {"lamina"}
    assert all(np.array_equal(got[k], parts[k]) for k in got)
    with pytest.raises(ValueError, match="no vertex labeled 'body'"):
        M.parts_of_vertebra(np.zeros(len(pts), int), names, ~other)


def test_measure_spine_two_levels():
    """Two copies of the synthetic vertebra, the second 40 mm higher, labeled per vertex: the same numbers."""
    pts, faces, parts, sup, inf = synthetic_vertebra()
    n = len(pts)
    both = np.vstack([pts, pts + [0.0, 0.0, 40.0]])
    region = np.zeros(n, int)
    for k, idx in parts.items():
        region[idx] = M.PARTS.index(k)
    out = M.measure_spine(
        both,
        np.vstack([faces, faces + n]),
        np.tile(region, 2),
        np.repeat([0, 1], n),
        M.PARTS,
        ("L4", "L5"),
        {"L4": (sup, inf), "L5": (sup + n, inf + n)},
    )
    wide = out.pivot(index="quantity", columns="level", values="value")
    np.testing.assert_allclose(wide["L4"], wide["L5"], atol=1e-9)
    assert wide.loc["endplate_width_upper", "L5"] == pytest.approx(W, abs=1e-6)


def test_frame_is_the_vertebra_frame():
    """Anterior = body centre minus canal centre, superior = endplate normal, whatever the pose."""
    pts, faces, parts, sup, inf = synthetic_vertebra()
    moved, rot = _moved(pts, seed=11)
    frame = M.vertebra_frame(moved, sup, inf, parts["body"], M.canal_centre(moved, parts))
    np.testing.assert_allclose(frame.anterior, rot[:, 0], atol=1e-9)
    np.testing.assert_allclose(frame.right, -rot[:, 1], atol=1e-9)
    np.testing.assert_allclose(frame.superior, rot[:, 2], atol=1e-9)
    np.testing.assert_allclose(frame.local(moved[parts["body"]]), pts[parts["body"]] * [1.0, -1.0, 1.0], atol=1e-9)


def test_wedged_body_alone():
    """A body alone (no labels, endplates found from the normals): trapezoid prism 27 mm high in front and
    23 mm behind, 40 x 30 mm endplates; heights are read at the rims, along the mean endplate normal."""
    pts, faces = _box((-D / 2, -W / 2, -1.0), (D / 2, W / 2, 1.0))
    ha, hp = 27.0, 23.0
    pts[:, 2] *= 0.5 * (hp + (ha - hp) * (pts[:, 0] + D / 2) / D)
    moved, rot = _moved(pts, seed=5)
    m = M.measure_body(moved, faces, up_hint=rot[:, 2] + 0.2 * rot[:, 0], anterior_hint=rot[:, 0] - 0.3 * rot[:, 2])
    assert m["body_height_anterior"] == pytest.approx(ha, abs=1e-6)
    assert m["body_height_posterior"] == pytest.approx(hp, abs=1e-6)
    assert m["endplate_width_upper"] == pytest.approx(W, abs=1e-6)
    # the tilted endplate spans 30 mm along the frame's anterior axis (its own length is 30 / cos 3.8 deg)
    assert m["endplate_depth_upper"] == pytest.approx(D, abs=1e-6)


def test_compare_with_reference_verdicts():
    ref = pd.DataFrame(
        [
            {
                "level": "L1",
                "quantity": "endplate_width_upper",
                "mean": 41.2,
                "sem": 1.03,
                "n": 12,
                "unit": "mm",
                "source": "P",
            },
            {"level": "L1", "quantity": "pedicle_width", "mean": 8.7, "sd": 2.3, "unit": "mm", "source": "Z"},
            {"level": "L3", "quantity": "facet_sup_transverse", "low": 40, "high": 56, "unit": "deg", "source": "M"},
            {"level": "T11", "quantity": "endplate_width_upper", "mean": 35.2, "unit": "mm", "source": "F"},
            {"level": "L2", "quantity": "canal_width", "mean": 23.8, "sd": 1.0, "unit": "mm", "source": "P"},
        ]
    )
    measured = pd.DataFrame(
        {
            "level": ["L1", "L1", "L3", "T11", "L1"],
            "quantity": [
                "endplate_width_upper",
                "pedicle_width",
                "facet_sup_transverse",
                "endplate_width_upper",
                "canal_depth",
            ],
            "value": [48.3, 13.4, 39.0, 35.0, 17.0],
        }
    )
    out = M.compare_with_reference(measured, ref).set_index(["level", "quantity"])
    # SEM 1.03 over 12 spines -> SD 3.568 -> 41.2 +- 7.14 = 34.06 .. 48.34: 48.3 is inside
    assert out.loc[("L1", "endplate_width_upper"), "ref_high"] == pytest.approx(41.2 + 2 * 1.03 * np.sqrt(12))
    assert out.loc[("L1", "endplate_width_upper"), "verdict"] == "inside"
    assert out.loc[("L1", "pedicle_width"), "verdict"] == "outside"  # 8.7 + 2 x 2.3 = 13.3 < 13.4
    assert out.loc[("L3", "facet_sup_transverse"), "verdict"] == "outside"  # below the 40..56 range
    assert out.loc[("T11", "endplate_width_upper"), "verdict"] == "no interval"  # a mean without dispersion
    assert out.loc[("L2", "canal_width"), "verdict"] == "not measured"
    assert out.loc[("L1", "canal_depth"), "verdict"] == "no reference"


def test_reference_table_is_consistent():
    ref = M.reference_table()
    assert set(ref["unit"]) <= {"mm", "deg"}
    assert (ref["unit"] == ref["quantity"].map(M.UNITS)).all()
    assert ref["source"].notna().all() and ref["provenance"].notna().all()
    # every row gives a value: a mean or a range
    assert (ref["mean"].notna() | (ref["low"].notna() & ref["high"].notna())).all()
    # Panjabi 1992 lumbar upper endplate width grows from L1 to L5 (41.2 .. 47.3 mm)
    epw = ref[(ref["quantity"] == "endplate_width_upper") & ref["source"].str.startswith("Panjabi et al. 1992")]
    assert list(epw["level"]) == ["L1", "L2", "L3", "L4", "L5"]
    assert np.all(np.diff(epw["mean"].to_numpy()) > 0)


# ---- real lumbar bodies: Visible Human Male via Remus et al. 2021 (OBJ in metres, +X anterior, +Z superior)
REMUS_REPO = Path(
    os.environ.get("SPINECOHORT_REMUS_REPO", "/work/.mirror/RemusR9+artisynth_lumbosacralSpineModel/repo")
)
REMUS_RB = "hybrid_LSS_model/src/artisynth/models/passiveComponents_PlosOne/geometry/RB"


def _remus_body(level: str, suffix: str = "_body") -> tuple[np.ndarray, np.ndarray]:
    """The welded surface (mm) of ``<level><suffix>.obj`` (a body by default), read from the upstream git
    directory (never copied here)."""
    text = subprocess.run(
        ["git", f"--git-dir={REMUS_REPO}", "show", f"HEAD:{REMUS_RB}/{level}{suffix}.obj"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    v = np.array([ln.split()[1:4] for ln in text.splitlines() if ln.startswith("v ")], float) * 1000.0
    f = np.array(
        [[int(t.split("/")[0]) - 1 for t in ln.split()[1:4]] for ln in text.splitlines() if ln.startswith("f ")]
    )
    # the OBJ repeats a position per normal/texture index: weld to a closed surface
    uniq, inv = np.unique(np.round(v, 4), axis=0, return_inverse=True)
    return uniq, inv.ravel()[f]


@pytest.mark.skipif(not REMUS_REPO.exists(), reason="the Remus 2021 repository is not on this machine")
def test_remus_lumbar_bodies_against_panjabi_1992():
    """Superior endplate width (EPWu) and posterior body height (VBHp) of the Visible Human Male's L1-L5
    against Panjabi 1992's mean +- 2 SD (SD = SEM x sqrt(12)): EPWu L1 34.1-48.3, L2 37.5-47.7, L3 38.0-50.2,
    L4 38.3-54.9, L5 39.0-55.6 mm; VBHp L1 17.4-30.2, L2 17.7-30.9, L3 16.2-31.4, L4 16.5-31.7,
    L5 16.3-29.5 mm.  This donor (a tall adult male) has wide bodies: his L2 endplate, 48.4 mm, is 0.7 mm
    wider than the interval; every other cell is inside."""
    rows = []
    for level in ("L1", "L2", "L3", "L4", "L5"):
        pts, faces = _remus_body(level)
        m = M.measure_body(pts, faces, up_hint=[0, 0, 1], anterior_hint=[1, 0, 0])
        rows += [{"level": level, "quantity": k, "value": v} for k, v in m.items()]
    measured = pd.DataFrame(rows)
    ref = M.reference_table()
    ref = ref[ref["source"].str.startswith("Panjabi et al. 1992")]
    ref = ref[ref["quantity"].isin(["endplate_width_upper", "body_height_posterior"])]
    out = M.compare_with_reference(measured, ref)
    out = out[out["verdict"] != "no reference"].set_index(["level", "quantity"])
    assert len(out) == 10
    outside = sorted(out.index[out["verdict"] == "outside"])
    assert outside == [("L2", "endplate_width_upper")]
    assert out.loc[("L2", "endplate_width_upper"), "value"] == pytest.approx(48.4, abs=0.3)
    # physiology the numbers must show: L5 is wedged (anterior taller than posterior), endplates widen caudally
    by = measured.set_index(["level", "quantity"])["value"]
    assert by[("L5", "body_height_anterior")] - by[("L5", "body_height_posterior")] > 5.0
    assert by[("L5", "endplate_width_upper")] > by[("L1", "endplate_width_upper")]


@pytest.mark.skipif(not REMUS_REPO.exists(), reason="the Remus 2021 repository is not on this machine")
def test_remus_superior_facets_against_masharawi_2004():
    """Superior articular facets of L2-L5 (Remus's ``L*_PD[lr]_a`` patches, both sides symmetrised upstream) in
    the frame of their own body: transverse angle to the mid-sagittal plane.  An independent estimate, the
    chord across a 3 mm transverse slab through the patch centre, agrees within 1.5 deg.  Against Masharawi
    2004 (T12-L2 26-34 deg, L3-L5 40-56 deg) these facets are more sagittal: L2 25.0 deg (1 deg under), L3 27.4,
    L4 25.2 and L5 38.4 deg, all outside -- a property of this reference geometry the FE facets inherit."""
    expected = {"L2": 25.0, "L3": 27.4, "L4": 25.2, "L5": 38.4}
    rows = []
    for level, want in expected.items():
        pts, faces = _remus_body(level)
        sup, inf, _ = M.endplate_sets(pts, faces, [0, 0, 1])
        frame = M.vertebra_frame(pts, sup, inf, np.arange(len(pts)), anterior_hint=[1, 0, 0])
        for side in ("l", "r"):
            q = frame.local(_remus_body(f"{level}_PD{side}_a", suffix="")[0])
            transverse, _ = M.facet_angles(q)
            slab = q[np.abs(q[:, 2] - q[:, 2].mean()) < 1.5, :2]
            u = np.linalg.svd(slab - slab.mean(axis=0), full_matrices=False)[2][0]
            assert transverse == pytest.approx(np.degrees(np.arctan2(abs(u[1]), abs(u[0]))), abs=1.5)
            assert transverse == pytest.approx(want, abs=0.3)
        rows.append({"level": level, "quantity": "facet_sup_transverse", "value": transverse})
    ref = M.reference_table()
    out = M.compare_with_reference(pd.DataFrame(rows), ref[ref["source"].str.startswith("Masharawi")])
    out = out[out["verdict"] != "not measured"]
    assert sorted(out["level"]) == ["L2", "L3", "L4", "L5"]
    assert set(out["verdict"]) == {"outside"}
