"""The cohort platform (spinecohort.web): server-side logic as unit tests, the data layer on the test
configuration's results (the session's ``test_run``), and the launcher's refusals over HTTP.  The page in
a real headless Chromium is ``test_web_browser.py``."""

import io
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import spinecohort
from spinecohort.web.data import (
    PlatformError,
    bounded_zip,
    filter_mask,
    histogram_counts,
    nearest_models,
    open_data,
)
from spinecohort.web.logic import histogram_svg, parse_more_ranges

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
    svg = histogram_svg({"PI": h}, {"PI": "Pelvic incidence (deg)"})
    assert svg.startswith("<svg") and "Pelvic incidence (deg)" in svg and svg.count("<rect") == 3 + 2


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
    page.state.per_page = 10
    page.update_rows()
    expect = data.table.sort_values("PI", ascending=False)["model_id"].head(10).tolist()
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
    assert "Pelvic incidence: min 60 exceeds max 50" in page.state.message
    page.state.f_PI_lo = page.state.f_PI_hi = ""
    page.apply_filter()
    assert page.state.message == "" and page.state.n_match == len(data.table)


def test_serve_warns_when_listening_beyond_this_machine(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "spinecohort.cli", "serve", "--host", "0.0.0.0", "--port", str(_free_port())]
        + ["--results", str(tmp_path / "none")]
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


# ------------------------------------------------------------------------------ labels and state checks
def test_labels_spell_out_names_units_and_gap_categories(data):
    from spinecohort.web.labels import empty_columns, explain, gap_words, label, label_with_unit

    assert label_with_unit("PI") == "Pelvic incidence (deg)" and label_with_unit("SVA_T1").endswith("(mm)")
    assert label("TK_T4T12") == "Thoracic kyphosis T4–T12" and label("DH_L4-L5") == "Disc height L4–L5"
    assert label("w2") == "Shape mode 2" and "standard deviations" in explain("w2")
    assert [gap_words(c) for c in ("P", "MD", "SD", None)] == [
        "proportioned",
        "moderately disproportioned",
        "severely disproportioned",
        "",
    ]
    t = pd.DataFrame({"a": [np.nan, np.nan], "b": [1.0, np.nan], "c": ["", ""], "d": ["x", ""]})
    assert empty_columns(t, ["a", "b", "c", "d"]) == ["a", "c"]
    # the test grid's virtual models have no measured GAP (no age): the column is not on the page
    gap_known = np.isfinite(data.table["GAP"].to_numpy(float)).any() if "GAP" in data.table else False
    from spinecohort.web.app import Platform

    page = Platform(data)
    assert ("GAP" in page.columns) == gap_known
    assert all(h["title"] and h["hover"] for h in page.state.headers if h["key"] not in ("model_id", "kind"))


@pytest.fixture(scope="module")
def page(data):
    from spinecohort.web.app import Platform

    return Platform(data)


@pytest.mark.parametrize(
    "changes, why",
    [
        ({"f_gap": ["<script>"]}, "f_gap: '<script>' is not one of"),
        ({"w_0": 99.0}, "w_0: 99.0 is outside -3 ... 3"),
        ({"w_0": True}, "expected a number, got bool"),
        ({"w_0": float("nan")}, "outside"),
        ({"per_page": -1}, "per_page: '-1' is not one of 10, 15, 25, 50, 100"),
        ({"sort_by": [{"key": "__class__", "order": "asc"}]}, "is not a column"),
        ({"f_PI_lo": "9" * 40}, "longer than 32"),
        ({"f_kind": ["virtual"]}, "is not one of"),
        ({"message": "you were hacked"}, "only '' may be set"),
        ({"n_match": 0}, "'n_match' is not a value the page sets"),
        ({"title": "x"}, "'title' is not a value the page sets"),
    ],
)
def test_state_checks_refuse_what_no_widget_sends(page, changes, why):
    from spinecohort.web.guard import refusal, state_rules

    got = refusal(state_rules(page), changes)
    assert got is not None and why in got, got


def test_state_checks_pass_what_the_widgets_send(page):
    from spinecohort.web.guard import refusal, state_rules

    ok = {
        "f_PI_lo": "45.5",
        "f_PI_hi": "",
        "f_gap": [page.state.gap_choices[0]["value"]],
        "f_kind": "virtual",
        "w_0": -3.0,
        "w_1": 1.25,
        "per_page": 50,
        "page": 2,
        "sort_by": [{"key": "PI", "order": "desc"}],
        "model_input": "model_00005",
        "pat_PI": "55",
        "message": "",
        "f_other": "TK_T1T12 30:50",
    }
    assert refusal(state_rules(page), ok) is None


def test_origin_must_be_the_served_host():
    from spinecohort.web.launcher import host_of, origin_refusal

    allowed = {"127.0.0.1", "localhost", "::1"}
    assert host_of("127.0.0.1:8080") == "127.0.0.1" and host_of("[::1]:8080") == "::1"
    assert origin_refusal("http://127.0.0.1:8080", "127.0.0.1:8080", allowed) is None
    assert origin_refusal("https://localhost:8080", "localhost:8080", allowed) is None
    for origin, host, why in (
        ("http://evil.example.com", "127.0.0.1:8080", "is not this server"),
        ("http://127.0.0.1:9999", "127.0.0.1:8080", "is not this server"),  # another port: another origin
        (None, "127.0.0.1:8080", "no Origin"),
        ("http://evil.example.com:8080", "evil.example.com:8080", "Host"),  # a foreign name pointed here
    ):
        assert why in origin_refusal(origin, host, allowed)


def test_trame_reads_every_access_key_as_given():
    from trame.app import get_server

    from spinecohort.web.launcher import trame_argv

    parser = get_server("spinecohort-key-test", client_type="vue3").cli
    # keys as secrets.token_urlsafe makes them: one in 64 starts with '-', which a separate argv word loses
    for key in ("-Zx9_kq", "--kq", "_a-b", "plain"):
        args, _ = parser.parse_known_args(trame_argv(key))
        assert args.authKey == key


def test_a_session_ends_on_idle_on_a_left_tab_and_later_on_a_first_load():
    from spinecohort.web.launcher import FIRST_LOAD_GRACE_S, RECONNECT_GRACE_S, Session, ending

    def sess(quiet_s, n_ws, connected):
        return Session("s", 1, 1, created=0.0, last_active=1000.0 - quiet_s, n_ws=n_ws, connected=connected)

    idle = 1800.0
    # an open websocket keeps a session until the idle timeout, whatever the graces
    assert ending(sess(idle - 1, 1, True), 1000.0, idle) is None
    assert ending(sess(idle + 1, 1, True), 1000.0, idle) == "idle for 1800 s"
    # a closed tab: the reconnect grace (a page reload comes back well within it)
    assert ending(sess(RECONNECT_GRACE_S - 1, 0, True), 1000.0, idle) is None
    assert ending(sess(RECONNECT_GRACE_S + 1, 0, True), 1000.0, idle) == "its browser left"
    # a page still loading its client code, quiet for longer than a reload's grace, is kept
    assert ending(sess(RECONNECT_GRACE_S + 1, 0, False), 1000.0, idle) is None
    assert ending(sess(FIRST_LOAD_GRACE_S + 1, 0, False), 1000.0, idle) == "its page never connected"
    # both graces are bounded by a shorter idle timeout
    assert ending(sess(11, 0, False), 1000.0, 10.0) == "idle for 10 s"


def test_xlsx_of_the_table_reads_back_equal(data):
    from spinecohort.web.logic import xlsx_bytes

    t = data.table
    back = pd.read_excel(io.BytesIO(xlsx_bytes(t)), sheet_name="selection")
    assert list(back.columns) == list(t.columns) and len(back) == len(t)
    np.testing.assert_allclose(back["PI"].to_numpy(float), np.round(t["PI"].to_numpy(float), 4), rtol=0, atol=1e-12)
    assert back["model_id"].tolist() == t["model_id"].tolist()
    assert back["repaired"].astype(bool).tolist() == t["repaired"].astype(bool).tolist()


def test_a_live_shape_deck_is_the_checked_shape_of_its_weights(data, tmp_path):
    from spinecohort.fe.inp_template import read_inp_nodes
    from spinecohort.personalize.cohort import personalized_hex

    w = np.array([1.5, -0.5, 0.0])
    path = tmp_path / "live.inp"
    path.write_bytes(data.weights_deck(w))
    _, xyz = read_inp_nodes(path)
    pts, _ = personalized_hex(data.template, data.hex_ssm, w, 0.0)
    assert np.abs(xyz[: len(pts)] - pts).max() < 1e-5  # printed with 6 decimals
    with pytest.raises(PlatformError, match="within \\+-3 SD"):
        data.weights_deck([4.0, 0.0, 0.0])


# ------------------------------------------------------------------------------ the launcher over HTTP
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_server(url, proc, log, timeout_s=60.0) -> float:
    """Seconds until ``url`` answers; fails with the server's log if it stops or stays silent."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout_s:
        try:
            urllib.request.urlopen(url, timeout=1)
            return time.perf_counter() - t0
        except OSError:
            assert proc.poll() is None, log.read_text()
            time.sleep(0.25)
    raise AssertionError(f"the server did not answer in {timeout_s:g} s:\n{log.read_text()}")


def _serve(test_run, port, *extra):
    cmd = [sys.executable, "-m", "spinecohort.cli", "serve", "--port", str(port), *extra]
    cmd += ["--config", str(test_run / "config" / "config.yaml"), "--results", str(test_run / "results")]
    return cmd


def test_a_port_in_use_is_one_line(test_run):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        proc = subprocess.run(_serve(test_run, port), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        f"spinecohort: error: port {port} on 127.0.0.1 is already in use (another spinecohort serve?); "
        "choose one with --port"
    )


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *a, **k):
        return None


def _get(url, headers=None):
    """(status, location, body) of a GET without following redirects."""
    opener = urllib.request.build_opener(_NoRedirect)
    try:
        with opener.open(urllib.request.Request(url, headers=headers or {}), timeout=30) as r:
            return r.status, r.headers.get("Location"), r.read().decode(errors="replace")
    except urllib.error.HTTPError as e:
        return e.code, e.headers.get("Location"), e.read().decode(errors="replace")


def _ws_status(url, origin) -> int:
    """HTTP status of a websocket handshake to ``url`` sent with ``origin`` (101 = accepted)."""
    import asyncio

    import aiohttp

    async def go():
        headers = {"Origin": origin} if origin else {}
        async with aiohttp.ClientSession() as s:
            try:
                async with s.ws_connect(url, headers=headers) as ws:
                    await ws.close()
                    return 101
            except aiohttp.WSServerHandshakeError as e:
                return e.status

    return asyncio.run(go())


def test_sessions_are_bounded_end_when_idle_and_refuse_other_origins(test_run, tmp_path):
    port = _free_port()
    log = tmp_path / "serve.log"
    # one session at most, ending 3 s after its last action
    cmd = _serve(test_run, port, "--max-sessions", "1", "--idle-timeout", "0.05")
    proc = subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_for_server(base + "/status", proc, log)
        status, loc, _ = _get(base + "/")
        assert status == 302 and loc.startswith("/s/"), (status, loc)
        sid = loc.split("/")[2]
        ws = f"ws://127.0.0.1:{port}/s/{sid}/ws"
        assert _ws_status(ws, "http://evil.example.com") == 403
        assert _ws_status(ws, f"http://127.0.0.1:{port + 1}") == 403  # another port is another origin
        assert _ws_status(ws, f"http://127.0.0.1:{port}") == 101  # the page's own origin
        assert _get(base + f"/s/{sid}/ws")[0] == 400  # a plain GET of the websocket's address
        assert _get(base + "/", {"Host": f"evil.example.com:{port}"})[0] == 403  # a foreign name for this host
        status, _, body = _get(base + "/")  # the one session is in use
        assert status == 503 and "All 1 sessions" in body
        t0 = time.time()
        while time.time() - t0 < 15 and '"sessions": 0' not in _get(base + "/status")[2]:
            time.sleep(0.5)
        assert '"sessions": 0' in _get(base + "/status")[2]  # it ended after 3 s without an action
        assert _get(base + "/")[0] == 302  # and its place is free again
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=20)
    text = log.read_text()
    assert "refused a websocket to session" in text and "Origin 'http://evil.example.com'" in text
    assert "idle for 3 s" in text and "Traceback" not in text, text


def test_the_page_header_names_the_source_without_the_servers_path(data):
    from spinecohort.web.data import describe

    line = describe(data)
    where = data.src.origin.partition(" ")[2]
    assert where.startswith("/") and where not in line  # a visitor learns no server path
    assert line.startswith(f"results {Path(where).name}: ") and "virtual models" in line
