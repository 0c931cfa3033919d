"""The cohort platform (spinecohort.web): server-side logic as unit tests, then the page in a real headless
Chromium on the test configuration's results (the session's ``test_run``)."""

import io
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import spinecohort
from spinecohort.web.app import histogram_svg, parse_more_ranges
from spinecohort.web.data import (
    PlatformError,
    bounded_zip,
    filter_mask,
    histogram_counts,
    nearest_models,
    open_data,
)

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
REPO = Path(spinecohort.__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------ pure logic
@pytest.fixture
def table():
    rng = np.random.default_rng(3)
    n = 2000
    return pd.DataFrame(
        {
            "model_id": [f"model_{i:05d}" for i in range(n)],
            "PI": rng.normal(55, 10, n),
            "PT": rng.normal(20, 6, n),
            "GAP_category": rng.choice(["P", "MD", "SD"], n),
            "repaired": rng.random(n) < 0.1,
        }
    ).assign(PI=lambda t: t["PI"].where(np.arange(n) % 97 != 0))  # some NaN: never match a range


def test_filter_mask_equals_the_pandas_expression(table):
    m = filter_mask(table, {"PI": (50.0, 60.0), "PT": (None, 25.0)}, {"GAP_category": ["P", "MD"]}, {"repaired": False})
    expect = (
        table["PI"].between(50, 60) & (table["PT"] <= 25) & table["GAP_category"].isin(["P", "MD"]) & ~table["repaired"]
    )
    assert m.sum() == expect.sum() and np.array_equal(m, expect.to_numpy())
    assert 100 < m.sum() < 1000  # a real selection, neither everything nor nothing
    # no filter keeps every row; an empty category list and flag None do not filter
    assert filter_mask(table, {}, {"GAP_category": []}, {"repaired": None}).all()


def test_more_ranges_use_the_query_grammar():
    assert parse_more_ranges("TK_T1T12 30:50; DH_L4-L5 8:, w1 :0") == {
        "TK_T1T12": (30.0, 50.0),
        "DH_L4-L5": (8.0, None),
        "w1": (None, 0.0),
    }
    with pytest.raises(PlatformError, match="lower bound 5.0 exceeds upper bound 1.0"):
        parse_more_ranges("PI 5:1")
    with pytest.raises(PlatformError, match="not a range"):
        parse_more_ranges("PI fifty")


def test_nearest_models_rank_by_the_stated_normalized_distance():
    # SDs over the table: PI 11.18 deg, PT 5 deg (population SD).  c is 8 deg of PI from the target but 9 deg
    # = 1.8 SD of PT; d is 18 deg = 1.61 SD of PI but 0.2 SD of PT: in SD units d is the nearer one
    t = pd.DataFrame({"model_id": list("abcd"), "PI": [40.0, 50.0, 60.0, 70.0], "PT": [10.0, 20.0, 10.0, 20.0]})
    s_pi, s_pt = np.std(t["PI"]), np.std(t["PT"])
    near = nearest_models(t, {"PI": 52.0, "PT": 19.0}, k=2)
    assert near["model_id"].tolist() == ["b", "d"]
    # d = sqrt(mean(((x - t) / s)^2)): b is (-2 / s_pi, 1 / s_pt) away
    assert near["distance"].iloc[0] == pytest.approx(np.sqrt(((2 / s_pi) ** 2 + (1 / s_pt) ** 2) / 2), rel=1e-12)
    with pytest.raises(PlatformError):
        nearest_models(t, {})


def test_bounded_zip_refuses_too_many_and_too_large():
    built = []
    blob = lambda name: built.append(name) or name.encode() * 100  # noqa: E731
    z = bounded_zip(["a.inp", "b.inp"], blob, max_models=2, progress=lambda d, n: built.append((d, n)))
    with zipfile.ZipFile(io.BytesIO(z)) as f:
        assert f.namelist() == ["a.inp", "b.inp"] and f.read("b.inp") == b"b.inp" * 100
    assert built == ["a.inp", (1, 2), "b.inp", (2, 2)]
    built.clear()
    with pytest.raises(PlatformError, match="at most 2"):
        bounded_zip(["a", "b", "c"], blob, max_models=2)
    assert built == []  # refused before building anything
    rnd = lambda name: np.random.default_rng(0).bytes(5000)  # noqa: E731  (incompressible)
    with pytest.raises(PlatformError, match="passed 0 MB after 2 models"):
        bounded_zip(["a", "b", "c"], rnd, max_models=3, max_bytes=8000)


def test_histogram_counts_share_edges_and_count_the_selection():
    v = np.array([0.0, 1.0, 2.0, 3.0, np.nan])
    h = histogram_counts(v, np.array([True, False, True, False, True]), bins=3)
    assert h["edges"].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert h["all"].tolist() == [1, 1, 2] and h["selected"].tolist() == [1, 0, 1]  # NaN counts nowhere
    svg = histogram_svg({"PI": h}, {"PI": "deg"})
    assert svg.startswith("<svg") and "PI [deg]" in svg and svg.count("<rect") == 3 + 2


# ------------------------------------------------------------------------------- on the test results
@pytest.fixture(scope="module")
def data(test_run):
    return open_data(results=test_run / "results", config=test_run / "config" / "config.yaml")


def test_ids_are_validated_never_paths(data):
    assert data.check_id("model_00013") == "model_00013"
    assert data.check_id("P01") == "P01"  # a known patient
    for bad, why in (
        ("model_00027", "outside the grid of 27 models"),
        ("../../etc/passwd", "not a model ID"),
        ("model_13", "not a model ID"),
        ("P99", "not a model ID"),
        ("/tmp/x.inp", "not a model ID"),
    ):
        with pytest.raises(PlatformError, match=why):
            data.check_id(bad)
    with pytest.raises(PlatformError, match="within \\+-3 SD"):
        data.check_weights([0.0, 3.5, 0.0])
    with pytest.raises(PlatformError, match="PI \\(60\\) must equal PT \\+ SS"):
        data.check_targets({"PI": "60", "PT": "20", "SS": "30"})
    assert data.check_targets({"PT": "20", "SS": "30", "LL": ""}) == {"PT": 20.0, "SS": 30.0, "PI": 50.0}


def test_table_holds_the_virtual_cohort_and_the_personalized_models(data, test_run):
    virtual = pd.read_csv(test_run / "results" / "virtual_cohort.csv")
    pers = pd.read_csv(test_run / "results" / "personalized" / "personalization.csv")
    fit = pers[pers["method"] == "fit"]
    t = data.table
    assert len(t) == len(virtual) + len(fit) == 27 + 8
    p01 = t[t["model_id"] == "P01"].iloc[0]
    assert p01["PI"] == pytest.approx(fit.set_index("ID").loc["P01", "PI_achieved"])
    assert p01["w1"] == pytest.approx(fit.set_index("ID").loc["P01", "b1"])


def test_downloads_equal_spinecohort_export_byte_for_byte(data, test_run, tmp_path):
    for fmt in ("inp", "stl", "vtu"):
        out = tmp_path / f"cli.{fmt}"
        subprocess.run(
            [sys.executable, "-m", "spinecohort.cli", "export", "model_00005", "--format", fmt, "--out", str(out)]
            + ["--config", str(test_run / "config" / "config.yaml"), "--results", str(test_run / "results")],
            check=True,
            capture_output=True,
        )
        name, payload = data.model_file("model_00005", fmt)
        assert name == f"model_00005.{fmt}" and payload == out.read_bytes()
    name, payload = data.model_file("P03", "inp")  # a patient's deck is the file personalize wrote
    assert payload == (test_run / "results" / "personalized" / "P03.inp").read_bytes()
    with zipfile.ZipFile(io.BytesIO(data.decks_zip(["model_00005", "P03"]))) as z:
        assert z.read("model_00005.inp") == (tmp_path / "cli.inp").read_bytes()


def test_the_continuous_fit_and_its_deck_equal_spinecohort_personalize(data, test_run, tmp_path):
    targets = data.check_targets({"PI": "55", "PT": "22", "LL": "40"})
    assert targets == {"PI": 55.0, "PT": 22.0, "LL": 40.0, "SS": 33.0}  # SS = PI - PT
    res = data.fit(targets)
    out = tmp_path / "cli.inp"
    proc = subprocess.run(
        [sys.executable, "-m", "spinecohort.cli", "personalize", "--PI", "55", "--PT", "22", "--LL", "40"]
        + ["--out", str(out), "--config", str(test_run / "config" / "config.yaml")]
        + ["--results", str(test_run / "results")],
        check=True,
        capture_output=True,
        text=True,
    )
    assert f"weights (SD): {np.round(res.weights, 4).tolist()}" in proc.stdout
    assert data.fitted_deck(targets, res) == out.read_bytes()


def test_live_shape_is_the_hex_ssm_formula(data):
    w = np.array([0.7, -1.2, 2.5])
    expect = data.hex_ssm.mean + np.einsum("m,mnc->nc", w, data.hex_ssm.fields[:3])
    np.testing.assert_allclose(data.live_points(w), expect, rtol=0, atol=1e-9)


def test_table_pages_sort_server_side(data):
    from spinecohort.web.app import Platform

    page = Platform(data)
    page.state.sort_by = [{"key": "PI", "order": "desc"}]
    page.state.per_page = 5
    page.update_rows()
    expect = data.table.sort_values("PI", ascending=False)["model_id"].head(5).tolist()
    assert [r["model_id"] for r in page.state.rows] == expect
    page.state.f_other = "PT 20:"  # a filtered table
    page.apply_filter()
    n = int((data.table["PT"] >= 20).sum())
    assert page.state.n_match == n and 0 < n < len(data.table)
    # unreadable filters: a message, and the last valid selection stays
    for bad, why in (("PT twenty", "not a range"), ("XX 1:2", "no numeric column 'XX'")):
        page.state.f_other = bad
        page.apply_filter()
        assert why in page.state.message and page.state.n_match == n
    page.state.f_other, page.state.f_PI_lo, page.state.f_PI_hi = "", "60", "50"
    page.apply_filter()
    assert "PI: min 60 exceeds max 50" in page.state.message
    page.state.f_PI_lo = page.state.f_PI_hi = ""
    page.apply_filter()
    assert page.state.message == "" and page.state.n_match == len(data.table)


def test_serve_warns_when_listening_beyond_this_machine(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "spinecohort.cli", "serve", "--host", "0.0.0.0", "--results", str(tmp_path / "none")]
        + ["--config", str(REPO / "config" / "config.yaml")],
        capture_output=True,
        text=True,
    )
    assert "WARNING: listening on 0.0.0.0 exposes the platform" in proc.stderr
    assert proc.returncode == 2 and "is not a results folder" in proc.stderr  # and nothing is served


def test_a_release_bag_serves_in_place_and_says_what_is_missing(test_run, tmp_path):
    bag = tmp_path / "bag"
    shutil.copytree(test_run / "results" / "release", bag)
    before = {p: p.stat().st_mtime_ns for p in bag.rglob("*")}
    d = open_data(release=bag)
    assert len(d.virtual) == 27 and "personalization.csv" in " ".join(d.missing)
    name, payload = d.model_file("model_00004", "inp")
    ref = open_data(results=test_run / "results", config=test_run / "config" / "config.yaml")
    assert payload == ref.model_file("model_00004", "inp")[1]  # = `export --release` = `export`
    # the bag has the patients' decks but not the fit table: they are served from the decks
    assert (
        d.check_id("P02") == "P02" and d.model_file("P02", "inp")[1] == (bag / "data/personalized/P02.inp").read_bytes()
    )
    np.testing.assert_allclose(
        d.model_points("P02"), ref.model_points("P02"), rtol=0, atol=1e-5
    )  # printed deck precision
    assert {p: p.stat().st_mtime_ns for p in bag.rglob("*")} == before  # nothing written into the bag


# ------------------------------------------------------------------------------------- the browser
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(test_run, tmp_path_factory):
    if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
        pytest.skip("Chromium and chromedriver are not installed (scripts/install_system_deps.sh installs them)")
    port = _free_port()
    log = tmp_path_factory.mktemp("serve") / "serve.log"
    cmd = [sys.executable, "-m", "spinecohort.cli", "serve", "--port", str(port), "--max-zip", "5"]
    cmd += ["--config", str(test_run / "config" / "config.yaml"), "--results", str(test_run / "results")]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}/"
    try:
        for _ in range(120):
            try:
                urllib.request.urlopen(url, timeout=1)
                break
            except OSError:
                assert proc.poll() is None, log.read_text()
                time.sleep(0.25)
        else:
            raise AssertionError(f"the server did not answer in 30 s:\n{log.read_text()}")
        print(f"server answered after {time.perf_counter() - t0:.1f} s")
        yield {"url": url, "proc": proc, "log": log}
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=10)


@pytest.fixture(scope="module")
def browser(server, tmp_path_factory):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    downloads = tmp_path_factory.mktemp("downloads")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--window-size=1600,1100",
        "--enable-unsafe-swiftshader",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
    ):
        opts.add_argument(a)
    opts.add_experimental_option(
        "prefs",
        {
            "download.default_directory": str(downloads),
            "download.prompt_for_download": False,
            "profile.default_content_setting_values.automatic_downloads": 1,
        },
    )
    drv = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        drv.get(server["url"])
        _wait(lambda: drv.find_elements("id", "match-count"), 30, "the page")
        drv.downloads = downloads
        yield drv
    finally:
        drv.quit()


def _wait(cond, timeout=20.0, what="condition"):
    t0 = time.time()
    while time.time() - t0 < timeout:
        try:
            v = cond()
        except Exception:  # the page is updating under us: try again
            v = None
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _type(drv, element_id, text):
    from selenium.webdriver.common.keys import Keys

    el = drv.find_element("id", element_id)
    el.send_keys(Keys.CONTROL, "a")
    el.send_keys(Keys.DELETE)
    el.send_keys(text)
    return el


def _canvas_pixels(drv) -> np.ndarray:
    """The 3D canvas as an (H, W, 3) int array (an element screenshot: the page region of the canvas)."""
    from PIL import Image

    png = drv.find_element("css selector", "#view-box canvas").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)[2:-2, 2:-2]


def _drawn_share(px: np.ndarray) -> float:
    """Share of pixels differing (sum |dRGB| > 30) from the background, the commonest border colour."""
    border = np.concatenate([px[0], px[-1], px[:, 0], px[:, -1]])
    colours, counts = np.unique(border, axis=0, return_counts=True)
    bg = colours[np.argmax(counts)]
    return float((np.abs(px - bg).sum(axis=2) > 30).mean())


def test_browser_filter_select_slide_download(browser, server, test_run, tmp_path_factory):
    from selenium.webdriver.common.keys import Keys

    from spinecohort.fe.inp_template import read_inp_nodes
    from spinecohort.store.zarr_store import read_model

    drv = browser
    table = pd.concat(
        [
            pd.read_csv(test_run / "results" / "virtual_cohort.csv"),
            pd.read_csv(test_run / "results" / "personalized" / "personalization.csv")
            .query("method == 'fit'")
            .rename(columns={"PI_achieved": "PI", "ID": "model_id", "b1": "w1", "b2": "w2"}),
        ]
    )
    n_all = len(table)
    assert drv.find_element("id", "match-count").text.startswith(f"{n_all} of {n_all} models match")
    # 1. a range filter: the count equals pandas' on the same tables (virtual + personalized rows)
    lo = float(np.median(table["PI"]))
    expect = int((table["PI"] >= lo).sum())
    assert 0 < expect < n_all
    _type(drv, "f_PI_lo", f"{lo:.6f}")
    _wait(lambda: drv.find_element("id", "match-count").text.startswith(f"{expect} of {n_all}"), 10, "the count")
    _type(drv, "f_PI_lo", "")
    _wait(lambda: drv.find_element("id", "match-count").text.startswith(f"{n_all} of"), 10, "the reset count")
    drv.find_elements("css selector", "#table .model-link")[1].click()  # a click in the table shows that model
    _wait(lambda: drv.find_element("id", "param-PI").text != "", 15, "the clicked model")
    assert "model_00001" in drv.find_element("id", "shown").text

    # 2. select a model: its PI from the table in the parameter panel, a drawn (non-blank) 3D view
    model = "model_00005"
    pi = float(pd.read_csv(test_run / "results" / "virtual_cohort.csv").set_index("model_id").loc[model, "PI"])
    _type(drv, "model_input", model)
    drv.find_element("id", "show").click()
    _wait(lambda: drv.find_element("id", "param-PI").text == f"{round(pi, 2):g}", 15, "the parameter panel")
    share = _wait(lambda: (s := _drawn_share(_canvas_pixels(drv))) > 0.02 and s, 20, "a drawn canvas")
    assert 0.02 < share < 0.95, share
    time.sleep(1.0)  # let vtk.js settle the frame before the reference picture
    before = _canvas_pixels(drv)

    # 3. move mode 1's slider (keyboard: 30 steps of 0.05 SD = +1.5 SD): the picture changes
    thumb = drv.find_elements("css selector", "#view-box ~ .v-row .v-slider-thumb")[0]
    thumb.click()
    for _ in range(30):
        thumb.send_keys(Keys.ARROW_RIGHT)
    _wait(lambda: "live: hex SSM" in drv.find_element("id", "shown").text, 10, "the live shape")
    changed = _wait(
        lambda: (d := (np.abs(_canvas_pixels(drv) - before).sum(axis=2) > 30).mean()) > 0.002 and d, 15, "a change"
    )
    print(f"slider moved: {100 * changed:.1f} % of the canvas pixels changed")
    shot = tmp_path_factory.mktemp("artefacts") / "platform.png"
    drv.save_screenshot(str(shot))
    print(f"screenshot: {shot}")

    # 4. download the selected model's deck: its nodes are the store's coordinates
    _type(drv, "model_input", model)
    drv.find_element("id", "show").click()
    _wait(lambda: "live" not in drv.find_element("id", "shown").text, 10, "the stored model")
    drv.find_element("id", "dl-inp").click()
    deck = _wait(lambda: (p := drv.downloads / f"{model}.inp").is_file() and p.stat().st_size > 0 and p, 30, "the deck")
    time.sleep(0.5)
    ids, xyz = read_inp_nodes(deck)
    _, stored = read_model(test_run / "results" / "cohort.zarr", 5)
    # the template's nodes first (the facet-joint gap nodes follow them)
    n = len(stored)
    assert ids[:n].tolist() == list(range(1, n + 1)) and len(ids) > n
    xyz = xyz[:n]
    # the store rounds to 2^-10 mm (float32-q10, error <= 0.49 um); the deck prints 6 decimals
    assert np.abs(xyz - stored).max() < 1e-3

    # 5. the mean as a translucent overlay; a bounded zip of the filtered decks and the filtered table as CSV
    drv.find_element("xpath", "//button[normalize-space()='mean']").click()
    _wait(lambda: "overlay: the mean model" in drv.find_element("id", "shown").text, 10, "the overlay")
    _type(drv, "f_other", "w1 3:; w2 3:")
    sel = table[(table["w1"] >= 3) & (table["w2"] >= 3)]["model_id"].tolist()
    assert 0 < len(sel) <= 5  # the server's --max-zip
    _wait(lambda: drv.find_element("id", "match-count").text.startswith(f"{len(sel)} of"), 10, "the zip selection")
    drv.find_element("id", "dl-zip").click()
    zpath = _wait(lambda: (p := drv.downloads / "spinecohort_decks.zip").is_file() and p, 60, "the zip")
    time.sleep(0.5)
    with zipfile.ZipFile(zpath) as z:
        assert sorted(z.namelist()) == sorted(f"{m}.inp" for m in sel)
    drv.find_element("id", "dl-csv").click()
    cpath = _wait(lambda: (p := drv.downloads / "virtual_cohort_selection.csv").is_file() and p, 30, "the CSV")
    time.sleep(0.5)
    assert sorted(pd.read_csv(cpath)["model_id"]) == sorted(sel)
    _type(drv, "f_other", "")

    # 6. bad input: a message in the page, and the server keeps serving
    _type(drv, "model_input", "../../etc/passwd")
    drv.find_element("id", "show").click()
    _wait(lambda: "not a model ID" in drv.find_element("id", "message").text, 10, "the bad-ID message")
    _type(drv, "model_input", "model_99999")
    drv.find_element("id", "show").click()
    _wait(lambda: "outside the grid of 27 models" in drv.find_element("id", "message").text, 10, "the range message")
    for k, val in (("pat_PI", "60"), ("pat_PT", "20"), ("pat_SS", "30")):
        _type(drv, k, val)
    drv.find_element("id", "find").click()
    _wait(lambda: "must equal PT + SS" in drv.find_element("id", "message").text, 10, "the PI = PT + SS message")
    _type(drv, "pat_PI", "")
    drv.find_element("id", "find").click()
    _wait(lambda: "continuous model: weights" in drv.find_element("id", "fit-text").text, 60, "the fitted model")
    nearest = _wait(lambda: drv.find_elements("xpath", "//td[starts-with(normalize-space(), 'd = ')]"), 10, "nearest")
    assert len(nearest) == 5
    drv.find_element("id", "dl-fit").click()  # one click from the numbers to a deck
    fit = _wait(lambda: (p := drv.downloads / "personalized.inp").is_file() and p.stat().st_size > 0 and p, 60, "deck")
    time.sleep(0.5)
    assert read_inp_nodes(fit)[0][: len(stored)].tolist() == list(range(1, len(stored) + 1))
    assert server["proc"].poll() is None


def test_server_stops_cleanly(server):
    proc = server["proc"]
    assert proc.poll() is None
    os.killpg(proc.pid, signal.SIGINT)
    assert proc.wait(timeout=15) in (0, -signal.SIGINT)
