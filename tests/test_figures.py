"""Figures (spinecohort.figures, workflow/rules/figures.smk) and the Snakemake report.

The DAG's figures come from the session-wide test run (`test_run` in conftest.py, .test/config); the unit
tests render small images of their own on its template and hex SSM."""

import subprocess
import sys
from pathlib import Path

import matplotlib.colors
import numpy as np
import pandas as pd
import pytest
import yaml
from PIL import Image

from spinecohort.figures.cohort import parameter_histograms_figure, quality_summary_figure
from spinecohort.figures.models import part_model_figure, personalized_gallery_figure
from spinecohort.figures.render import (
    HEX_PART_STYLE,
    LIGAMENT_STYLE,
    SURFACE_STYLE,
    hex_boundary_faces,
    ligament_group,
    render_hex_model,
)
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate

ROOT = Path(__file__).resolve().parents[1]
TEST_FIGURES = yaml.safe_load((ROOT / ".test" / "config" / "config.yaml").read_text())["figures"]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# figure -> (width, height) in pixels. The SSM curves are sized in their plotting functions (7 x 4.2 in and
# 10 x 4 in at 150 dpi); every other size comes from the `figures` block of the test config.
EXPECTED_SIZES = {
    "ssm/compactness.png": (1050, 630),
    "ssm/quality.png": (1500, 600),
    "figures/mode_variation.png": tuple(TEST_FIGURES["window"]),
    "figures/mean_model_parts.png": tuple(TEST_FIGURES["parts_size"]),
    "figures/personalized_gallery.png": tuple(TEST_FIGURES["gallery_size"]),
    "figures/parameter_histograms.png": tuple(TEST_FIGURES["histogram_size"]),
    "figures/quality_summary.png": tuple(TEST_FIGURES["quality_size"]),
}


def _rgb(path):
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def _shaded_matches(img: np.ndarray, colour: str, tol: float = 12.0) -> int:
    """Pixels that are the colour under diffuse lighting: p = s * c for a brightness s in [0.3, 1.3], within
    tol (RGB units). Unlit lines satisfy this with s = 1."""
    c = 255 * np.array(matplotlib.colors.to_rgb(colour))
    p = img.reshape(-1, 3).astype(float)
    s = p @ c / (c @ c)
    resid = np.linalg.norm(p - s[:, None] * c, axis=1)
    return int(np.sum((resid < tol) & (s > 0.3) & (s < 1.3)))


def _exact_matches(img: np.ndarray, colour: str, tol: float = 10.0) -> int:
    c = 255 * np.array(matplotlib.colors.to_rgb(colour))
    return int(np.sum(np.linalg.norm(img.reshape(-1, 3).astype(float) - c, axis=1) < tol))


@pytest.fixture(scope="module")
def model(test_run):
    r = test_run / "results" / "template"
    return HexTemplate.load(r / "template.npz"), HexSSM.load(r / "hex_ssm.npz")


def test_boundary_faces_of_hex_blocks_closed_form():
    # one hex: 6 faces; two hexes sharing a face: 2 * 6 - 2 = 10; an n x n x n block: 6 n^2 outer quads
    cube = np.array([[0, 1, 2, 3, 4, 5, 6, 7]])
    assert len(hex_boundary_faces(cube)[0]) == 6
    two = np.array([[0, 1, 2, 3, 4, 5, 6, 7], [4, 5, 6, 7, 8, 9, 10, 11]])
    faces, owner = hex_boundary_faces(two)
    assert len(faces) == 10 and np.bincount(owner).tolist() == [5, 5]
    n = 3
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)  # [k, j, i]
    hexes = np.array(
        [
            [
                idx[k, j, i],
                idx[k, j, i + 1],
                idx[k, j + 1, i + 1],
                idx[k, j + 1, i],
                idx[k + 1, j, i],
                idx[k + 1, j, i + 1],
                idx[k + 1, j + 1, i + 1],
                idx[k + 1, j + 1, i],
            ]
            for k in range(n)
            for j in range(n)
            for i in range(n)
        ]
    )
    faces, owner = hex_boundary_faces(hexes)
    assert len(faces) == 6 * n * n  # 54; the central hex owns none
    assert 13 not in owner


def test_every_figure_is_a_nonblank_png_of_the_configured_size(test_run):
    r = test_run / "results"
    for name, size in EXPECTED_SIZES.items():
        path = r / name
        assert path.read_bytes()[:8] == PNG_SIGNATURE, name
        img = _rgb(path)
        assert (img.shape[1], img.shape[0]) == size, name
        # non-blank: a plain or nearly plain canvas has a grey-level SD of ~0 and a handful of colours; every
        # figure here has curves/renders over at least several percent of its area
        assert img.mean(axis=2).std() > 15, name
        packed = (img[..., 0].astype(np.int32) << 16) | (img[..., 1].astype(np.int32) << 8) | img[..., 2]
        assert len(np.unique(packed)) > 200, name  # distinct colours


def test_part_render_shows_every_tissue_and_ligament_colour(model, tmp_path):
    template, hex_ssm = model
    renders = part_model_figure(template, hex_ssm.mean, tmp_path / "parts.png", size_px=(900, 600), dpi=100)
    assert set(renders) == {"lateral", "section", "frontal", "detail"}
    every = np.concatenate([im.reshape(-1, 3) for im in renders.values()])[:, None, :]
    for _tissue, (label, colour) in HEX_PART_STYLE.items():
        # the thin ones (0.7 mm CEP, shell ring) show in the section and the disc close-up
        assert _shaded_matches(every, colour) > 100, label
    assert _shaded_matches(every, SURFACE_STYLE[1]) > 1000
    groups = set(ligament_group(template))
    assert groups == set(LIGAMENT_STYLE)  # all seven groups are in the template (ALL included)
    for g in groups:
        assert _exact_matches(every, LIGAMENT_STYLE[g][1]) > 10, g
    # control: the same view without ligaments has (almost) none of their colours, so the counts above are
    # the lines and not shading that happens to match
    bare = render_hex_model(template, hex_ssm.mean, "lateral", (300, 560), ligaments=False)
    with_lines = render_hex_model(template, hex_ssm.mean, "lateral", (300, 560))
    for g in ("SSL", "ISL", "ITL"):  # the groups seen from the side
        c = LIGAMENT_STYLE[g][1]
        assert _exact_matches(bare, c) <= 2 < 10 <= _exact_matches(with_lines, c), g


def test_gallery_from_a_personalization_table(model, tmp_path):
    template, hex_ssm = model
    k = hex_ssm.fields.shape[0]
    rng = np.random.default_rng(3)
    table = pd.DataFrame(
        {
            "ID": ["P07", "P07", "P02", "P02", "P05", "P05"],
            "method": ["projection", "fit"] * 3,
            **{f"b{j + 1}": rng.uniform(-2, 2, 6) for j in range(k)},
        }
    )
    out = tmp_path / "gallery.png"
    ids = personalized_gallery_figure(hex_ssm, template, table, out, size_px=(600, 400), dpi=100, n_models=2)
    assert ids == ["P07", "P02"]  # the first two "fit" rows, in the table's order
    img = _rgb(out)
    assert img.shape == (400, 600, 3) and img.mean(axis=2).std() > 15
    with pytest.raises(ValueError, match="no mode-weight columns"):
        personalized_gallery_figure(hex_ssm, template, table[["ID", "method"]], out)
    with pytest.raises(ValueError, match="no row with method == 'fit'"):
        personalized_gallery_figure(hex_ssm, template, table[table["method"] == "projection"], out)


def test_histograms_report_the_share_above_each_threshold(tmp_path):
    # PT = 0, 1, ..., 39 deg: 19 of 40 values (21 ... 39) are > 20 deg -> 47.5 %; patients 18, 22, 30 -> 2/3
    virtual = pd.DataFrame({"PT": np.arange(40.0), "PI": np.linspace(40, 80, 40)})
    patients = pd.DataFrame({"PT": [18.0, 22.0, 30.0], "PI": [50.0, 60.0, 70.0]})
    out = tmp_path / "h.png"
    shares = parameter_histograms_figure(
        virtual, patients, {"PT_min_deg": 20.0}, ["PI", "PT"], out, size_px=(800, 400), dpi=100
    )
    row = shares.set_index("parameter").loc["PT"]
    assert row["pct_virtual_above"] == pytest.approx(47.5) and row["pct_patients_above"] == pytest.approx(200 / 3)
    assert _rgb(out).shape == (400, 800, 3)
    # the threshold line is drawn in its colour
    assert _exact_matches(_rgb(out)[None], "#c0392b", tol=20) > 50
    with pytest.raises(ValueError, match=r"patients table has no column\(s\) \['SS'\]"):
        parameter_histograms_figure(virtual.assign(SS=1.0), patients, {}, ["SS"], out)
    with pytest.raises(ValueError, match="unknown inclusion criteria"):
        parameter_histograms_figure(virtual, patients, {"LL_max_deg": 5}, ["PT"], out)


def test_quality_summary_rejects_tables_without_the_columns(tmp_path):
    q = pd.DataFrame({"min_sj_before": [0.3], "min_sj_after": [0.3], "invalid_before": [0]})
    with pytest.raises(ValueError, match=r"lacks columns \['invalid_after', 'repaired'\]"):
        quality_summary_figure(q, pd.DataFrame(), tmp_path / "q.png")


def test_report_builds_with_every_figure(test_run):
    report = test_run / "report.html"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            "-s",
            str(ROOT / "Snakefile"),
            "--directory",
            str(test_run),
            "--report",
            str(report),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    html = report.read_text()
    assert len(html) > 500_000  # self-contained: the PNGs are embedded (the test figures alone are ~1 MB)
    for name in EXPECTED_SIZES:
        assert Path(name).name in html, name
    for category in (
        "1. Statistical shape model",
        "2. Hexahedral FE template",
        "3. Virtual cohort",
        "4. Personalized models",
    ):
        assert category in html, category
