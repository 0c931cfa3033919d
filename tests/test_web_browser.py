"""The cohort platform in a real headless Chromium (Selenium), on the test configuration's results (the
session's ``test_run``): two browser sessions at once on one ``spinecohort serve``, what a user does, and
what a hostile page or client does."""

import contextlib
import io
import os
import signal
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from test_web import wait_for_server

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"


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
    cmd += ["--max-sessions", "3", "--config", str(test_run / "config" / "config.yaml")]
    cmd += ["--results", str(test_run / "results")]
    proc = subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}/"
    try:
        print(f"server answered after {wait_for_server(url + 'status', proc, log):.1f} s")
        yield {"url": url, "proc": proc, "log": log, "port": port}
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=20)


def chrome(downloads: Path | None = None, size=(1600, 1000)):
    """A headless Chromium whose page area is ``size`` (CSS px) and whose downloads land in ``downloads``."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        f"--window-size={size[0]},{size[1]}",
        "--enable-unsafe-swiftshader",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
    ):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})  # the console, for a failure's report
    if downloads is not None:
        opts.add_experimental_option(
            "prefs",
            {
                "download.default_directory": str(downloads),
                "download.prompt_for_download": False,
                "profile.default_content_setting_values.automatic_downloads": 1,
            },
        )
    drv = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    # the window size includes the browser's frame: fix the page area itself
    drv.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": False},
    )
    drv.downloads = downloads
    return drv


def open_page(drv, url, server_log: Path | None = None):
    drv.get(url)
    # the first page of a session forks its process and loads the client; with the suite's other test process
    # beside it on 2 cores (another Chromium among them) that took over 60 s once: a bound on a hang, not a speed
    try:
        _wait(lambda: drv.find_elements("id", "match-count"), 180, "the page")
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{_page_report(drv, server_log)}") from None
    return drv


def _page_report(drv, server_log: Path | None) -> str:
    """What a timed-out page shows and what the server logged: the failure's own evidence."""
    lines = [f"address: {drv.current_url}"]
    with contextlib.suppress(Exception):
        lines.append("page text: " + drv.find_element("tag name", "body").text[:500].replace("\n", " | "))
    with contextlib.suppress(Exception):
        lines += ["browser console:", *(f"  {e['level']} {e['message'][:300]}" for e in drv.get_log("browser"))]
    if server_log is not None and server_log.exists():
        lines += ["server log (last 40 lines):", *server_log.read_text().splitlines()[-40:]]
    return "\n".join(lines)


def _session(server, tmp_path_factory):
    drv = chrome(tmp_path_factory.mktemp("downloads"))
    try:
        yield open_page(drv, server["url"], server["log"])
    finally:
        drv.quit()


browser = pytest.fixture(scope="module", name="browser")(_session)  # user A
browser_b = pytest.fixture(scope="module", name="browser_b")(_session)  # user B, at the same time


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


def _click(drv, el):
    """Click ``el`` after scrolling it to the middle of the page (off-screen rows of the table)."""
    drv.execute_script("arguments[0].scrollIntoView({block: 'center'});", el)
    el.click()


def _text(drv, element_id) -> str:
    return drv.find_element("id", element_id).text


def _show(drv, model):
    _type(drv, "model_input", model)
    _click(drv, drv.find_element("id", "show"))
    _wait(lambda: _text(drv, "shown").startswith(model), 15, f"{model} on screen")


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


def _download(drv, name, timeout=30):
    p = _wait(lambda: (q := drv.downloads / name).is_file() and q.stat().st_size > 0 and q, timeout, name)
    time.sleep(0.3)
    return p


def _table(test_run) -> pd.DataFrame:
    """The page's table from the files: the virtual cohort plus the personalized models."""
    pers = pd.read_csv(test_run / "results" / "personalized" / "personalization.csv").query("method == 'fit'")
    pers = pers.rename(columns={"PI_achieved": "PI", "PT_achieved": "PT", "ID": "model_id", "b1": "w1", "b2": "w2"})
    return pd.concat([pd.read_csv(test_run / "results" / "virtual_cohort.csv"), pers])


def test_browser_filter_select_slide_download(browser, server, test_run):
    from selenium.webdriver.common.keys import Keys

    from spinecohort.fe.inp_template import read_inp_nodes
    from spinecohort.store.zarr_store import read_model

    drv = browser
    table = _table(test_run)
    n_all = len(table)
    assert _text(drv, "match-count").startswith(f"{n_all} of {n_all} models match")
    # 1. a range filter: the count equals pandas' on the same tables (virtual + personalized rows)
    lo = float(np.median(table["PI"]))
    expect = int((table["PI"] >= lo).sum())
    assert 0 < expect < n_all
    _type(drv, "f_PI_lo", f"{lo:.6f}")
    _wait(lambda: _text(drv, "match-count").startswith(f"{expect} of {n_all}"), 10, "the count")
    _type(drv, "f_PI_lo", "")
    _wait(lambda: _text(drv, "match-count").startswith(f"{n_all} of"), 10, "the reset count")
    _click(drv, drv.find_elements("css selector", "#table .model-link")[1])  # a click in the table shows that model
    _wait(lambda: "model_00001" in _text(drv, "shown"), 15, "the clicked model")

    # 2. select a model: its PI from the table in the parameter panel, a drawn (non-blank) 3D view
    model = "model_00005"
    pi = float(pd.read_csv(test_run / "results" / "virtual_cohort.csv").set_index("model_id").loc[model, "PI"])
    _show(drv, model)
    _wait(lambda: _text(drv, "param-PI") == f"{round(pi, 2):g}", 15, "the parameter panel")
    share = _wait(lambda: (s := _drawn_share(_canvas_pixels(drv))) > 0.02 and s, 20, "a drawn canvas")
    assert 0.05 < share < 0.95, share  # the model fills a real part of the view
    time.sleep(1.0)  # let vtk.js settle the frame before the reference picture
    before = _canvas_pixels(drv)

    # 3. move mode 1's slider (keyboard: 30 steps of 0.05 SD = +1.5 SD): the picture changes
    thumb = drv.find_elements("css selector", "#sliders .v-slider-thumb")[0]
    thumb.click()
    for _ in range(30):
        thumb.send_keys(Keys.ARROW_RIGHT)
    _wait(lambda: "live shape" in _text(drv, "shown"), 10, "the live shape")
    changed = _wait(
        lambda: (d := (np.abs(_canvas_pixels(drv) - before).sum(axis=2) > 30).mean()) > 0.002 and d, 15, "a change"
    )
    print(f"slider moved: {100 * changed:.1f} % of the canvas pixels changed")

    # 4. download the selected model's deck: its nodes are the store's coordinates
    _show(drv, model)
    drv.find_element("id", "dl-inp").click()
    ids, xyz = read_inp_nodes(_download(drv, f"{model}.inp"))
    _, stored = read_model(test_run / "results" / "cohort.zarr", 5)
    n = len(stored)  # the template's nodes first (the facet-joint gap nodes follow them)
    assert ids[:n].tolist() == list(range(1, n + 1)) and len(ids) > n
    # the store rounds to 2^-10 mm (float32-q10, error <= 0.49 um); the deck prints 6 decimals
    assert np.abs(xyz[:n] - stored).max() < 1e-3

    # 5. the mean as a translucent overlay; a bounded zip of the filtered decks and the filtered table as CSV
    drv.find_element("id", "overlay-mean").click()
    _wait(lambda: "overlay: the mean model" in _text(drv, "shown"), 10, "the overlay")
    _type(drv, "f_other", "w1 3:; w2 3:")
    sel = table[(table["w1"] >= 3) & (table["w2"] >= 3)]["model_id"].tolist()
    assert 0 < len(sel) <= 5  # the server's --max-zip
    _wait(lambda: _text(drv, "match-count").startswith(f"{len(sel)} of"), 10, "the zip selection")
    drv.find_element("id", "dl-zip").click()
    with zipfile.ZipFile(_download(drv, "spinecohort_decks.zip", 60)) as z:
        assert sorted(z.namelist()) == sorted(f"{m}.inp" for m in sel)
    drv.find_element("id", "dl-csv").click()
    assert sorted(pd.read_csv(_download(drv, "virtual_cohort_selection.csv"))["model_id"]) == sorted(sel)
    _type(drv, "f_other", "")

    # 6. bad input: a message in the page, and the server keeps serving
    _type(drv, "model_input", "../../etc/passwd")
    drv.find_element("id", "show").click()
    _wait(lambda: "not a model ID" in _text(drv, "message"), 10, "the bad-ID message")
    _type(drv, "model_input", "model_99999")
    drv.find_element("id", "show").click()
    _wait(lambda: "outside the grid of 27 models" in _text(drv, "message"), 10, "the range message")
    for k, val in (("pat_PI", "60"), ("pat_PT", "20"), ("pat_SS", "30")):
        _type(drv, k, val)
    drv.find_element("id", "find").click()
    _wait(lambda: "must equal PT + SS" in _text(drv, "message"), 10, "the PI = PT + SS message")
    _type(drv, "pat_PI", "")
    drv.find_element("id", "find").click()
    _wait(lambda: "continuous model: weights" in _text(drv, "fit-text"), 60, "the fitted model")
    assert not drv.find_element("id", "message").is_displayed()  # the answer replaced the message
    nearest = _wait(lambda: drv.find_elements("xpath", "//td[starts-with(normalize-space(), 'd = ')]"), 10, "nearest")
    assert len(nearest) == 5
    drv.find_element("id", "dl-fit").click()  # one click from the numbers to a deck
    fit = _download(drv, "personalized.inp", 60)
    assert read_inp_nodes(fit)[0][: len(stored)].tolist() == list(range(1, len(stored) + 1))
    assert server["proc"].poll() is None


def test_enter_in_the_model_field_shows_the_model(browser):
    from selenium.webdriver.common.keys import Keys

    _type(browser, "model_input", "model_00003").send_keys(Keys.ENTER)
    _wait(lambda: _text(browser, "shown").startswith("model_00003"), 15, "the model shown by Enter")


def test_page_sizes_show_all_their_rows(browser, test_run):
    n_all = len(_table(test_run))
    opts = browser.execute_script("return window.trame.state.get('page_sizes')")
    assert -1 not in opts and max(opts) == 100  # no "All": 16,807 rows are too many for one page
    browser.execute_script("window.trame.state.set('per_page', 50)")  # as the page-size menu sets it
    _wait(lambda: len(browser.find_elements("css selector", "#table .model-link")) == n_all, 15, "all rows")
    footer = browser.find_element("css selector", "#table .v-data-table-footer").text
    assert f"1-{n_all} of {n_all}" in footer.replace("–", "-"), footer
    browser.execute_script("window.trame.state.set('per_page', 10)")
    _wait(lambda: len(browser.find_elements("css selector", "#table .model-link")) == 10, 15, "ten rows")


def test_downloads_and_panel_belong_to_the_shape_on_screen(browser, test_run):
    from spinecohort.fe.inp_template import read_inp_nodes
    from spinecohort.personalize.cohort import personalized_hex
    from spinecohort.web.data import open_data

    drv = browser
    _show(drv, "model_00005")
    _wait(lambda: drv.find_element("id", "param-PI").text, 10, "the panel")
    drv.execute_script("window.trame.state.set('w_0', 1.25)")  # what one slider move sends
    _wait(lambda: _text(drv, "shown").startswith("live shape"), 15, "the live shape")
    _wait(lambda: not drv.find_elements("id", "param-PI"), 10, "the stored model's parameters gone")
    assert drv.find_element("id", "live-note").is_displayed()
    assert not drv.find_element("id", "dl-stl").is_enabled() and drv.find_element("id", "dl-inp").is_enabled()
    w = [drv.execute_script(f"return window.trame.state.get('w_{i}')") for i in range(3)]
    drv.find_element("id", "dl-inp").click()
    name = "shape_w" + "_".join(f"{x:+.2f}" for x in w) + ".inp"
    _, xyz = read_inp_nodes(_download(drv, name))
    data = open_data(results=test_run / "results", config=test_run / "config" / "config.yaml")
    pts, _ = personalized_hex(data.template, data.hex_ssm, np.array(w), 0.0)
    assert w[0] == 1.25 and np.abs(xyz[: len(pts)] - pts).max() < 1e-5  # the shape on screen, not model_00005
    assert np.abs(pts - data.model_points("model_00005")).max() > 1.0


def test_a_message_is_cleared_by_the_next_success_and_patients_offer_only_their_deck(browser):
    drv = browser
    _type(drv, "model_input", "model_99999")
    drv.find_element("id", "show").click()
    _wait(lambda: "outside the grid" in _text(drv, "message"), 10, "the message")
    _show(drv, "P01")
    _wait(lambda: not drv.find_element("id", "message").is_displayed(), 10, "the message cleared")
    assert drv.find_element("id", "dl-inp").is_enabled()
    assert not drv.find_element("id", "dl-stl").is_enabled() and not drv.find_element("id", "dl-vtu").is_enabled()
    assert drv.find_elements("id", "param-PI")  # a patient's parameters, no blank lines
    assert all(td.text.strip() for td in drv.find_elements("css selector", "#params td:nth-child(2)"))
    # a refused zip (every model is more than --max-zip 5), then a successful CSV clears its message
    drv.execute_script("window.trame.trigger('download_zip', [])")
    _wait(lambda: "a zip holds at most 5" in _text(drv, "message"), 15, "the refused zip")
    drv.find_element("id", "dl-csv").click()
    _wait(lambda: not drv.find_element("id", "message").is_displayed(), 15, "the message cleared by the CSV")


def test_two_sessions_have_their_own_filters_models_and_sliders(browser, browser_b, server, test_run):
    a, b = browser, browser_b
    table = _table(test_run)
    n_all = len(table)
    lo = float(np.median(table["PI"]))
    n_a = int((table["PI"] >= lo).sum())
    n_b = int((table["PT"] >= 20).sum())
    assert n_a != n_b and 0 < n_b < n_all
    _type(a, "f_PI_lo", f"{lo:.6f}")
    _wait(lambda: _text(a, "match-count").startswith(f"{n_a} of"), 10, "A's count")
    _type(b, "f_other", "PT 20:")
    _wait(lambda: _text(b, "match-count").startswith(f"{n_b} of"), 10, "B's count")
    _show(a, "model_00002")
    _show(b, "model_00007")
    b.execute_script("window.trame.state.set('w_1', -2.0)")
    _wait(lambda: _text(b, "shown").startswith("live shape"), 10, "B's live shape")
    time.sleep(1.0)  # time for any update to reach the other page
    assert _text(a, "match-count").startswith(f"{n_a} of") and _text(a, "shown").startswith("model_00002")
    assert a.execute_script("return window.trame.state.get('w_1')") != -2.0
    assert a.execute_script("return window.trame.state.get('f_other')") == ""
    assert _text(b, "match-count").startswith(f"{n_b} of")
    # a new visitor starts from the defaults, not from A's or B's page
    c = open_page(chrome(), server["url"], server["log"])
    try:
        assert _text(c, "match-count").startswith(f"{n_all} of {n_all}")
        assert c.execute_script("return window.trame.state.get('model_input')") == ""
    finally:
        c.quit()
    _type(a, "f_PI_lo", "")
    _type(b, "f_other", "")


def test_an_invalid_value_is_refused_and_the_other_session_is_unaffected(browser, browser_b, server):
    a, b = browser, browser_b
    _wait(lambda: _text(b, "match-count").split()[0] == _text(b, "match-count").split()[2], 10, "B unfiltered")
    n_b = _text(b, "match-count")
    before = _text(a, "match-count")
    a.execute_script("window.trame.state.set('f_gap', ['<script>'])")
    _wait(lambda: "refused: f_gap" in _text(a, "message"), 10, "the refusal in A's page")
    assert a.execute_script("return window.trame.state.get('f_gap')") == []  # A's page got the server's value
    a.execute_script("window.trame.state.set('w_0', 1e9)")
    _wait(lambda: "refused: w_0" in _text(a, "message"), 10, "the slider refusal")
    a.execute_script("window.trame.trigger('download_zip', [1, 2, 3])")  # arguments no button sends
    _wait(lambda: "refused a call from a browser: download_zip" in server["log"].read_text(), 10, "the call refusal")
    assert _text(a, "match-count") == before and _text(b, "match-count") == n_b
    _wait(lambda: "No data available" not in b.find_element("id", "table").text, 5, "B's rows")
    log = server["log"].read_text()
    assert "refused a state update from a browser: f_gap: '<script>' is not one of" in log
    assert "Traceback" not in log, log


def test_a_page_of_another_origin_cannot_open_the_websocket(browser, server, tmp_path):
    """A page served from another port of this machine (another origin) opens this server's websocket: refused."""
    import functools
    import http.server
    import threading

    (tmp_path / "index.html").write_text("<p>elsewhere</p>")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    other = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    drv = chrome()
    try:
        drv.get(f"http://127.0.0.1:{other.server_address[1]}/index.html")
        sid = browser.current_url.split("/s/")[1].split("/")[0]
        drv.execute_script(
            "window.result = 'pending'; const ws = new WebSocket(arguments[0]);"
            "ws.onopen = () => { window.result = 'open'; }; ws.onerror = () => { window.result = 'refused'; };",
            f"ws://127.0.0.1:{server['port']}/s/{sid}/ws",
        )
        assert _wait(lambda: (r := drv.execute_script("return window.result")) != "pending" and r, 10) == "refused"
    finally:
        drv.quit()
        other.shutdown()
    log = server["log"].read_text()
    assert f"Origin 'http://127.0.0.1:{other.server_address[1]}' is not this server" in log


def test_server_stops_cleanly(server):
    proc = server["proc"]
    assert proc.poll() is None
    os.killpg(proc.pid, signal.SIGINT)
    assert proc.wait(timeout=20) in (0, -signal.SIGINT)
