"""The cohort platform at full scale: start time, filter and slider latency, xlsx time, memory per session.

    python benchmarks/bench_web.py [--work DIR] [--results DIR --config FILE] [--sessions 5] [--no-browser]
                                   [--screenshots DIR] [--churn]

Without ``--results`` it builds a stand-in results folder at the default scale: a real SSM of 6 synthetic
patients at the default surface resolution, the coarse hex template on its mean (64k nodes, 105k surface
triangles: the default model's size) with its hex SSM of 5 modes, and a **fabricated** 16,807-row table
(the real columns, values linear in the grid weights plus noise; parameters are not measured).  The
numbers are then those of the default scale, not of a real run's values.

Measures in-process: data load, page construction, filter latency (``filter_mask`` alone and the whole
page update: filter + sorted page of rows + histograms), the xlsx of the whole table, the live shape (hex
SSM formula + scene update).  With Chromium (``/usr/bin/chromium``): ``spinecohort serve`` start time to
the first HTTP answer and to a drawn 3D view, filter latency seen in the browser, the slider's server-side
time (sample + serialise + publish) and its end-to-end time to a changed canvas, and the memory (RSS, PSS,
private) of every process with N browser sessions open, each in its own Chromium.  ``--screenshots`` saves
the page at 1366 x 768 and 1920 x 1080; ``--churn`` follows one session's memory over 100 selections and
10 zips.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[1]


def make_results(work: Path) -> tuple[Path, Path]:
    """The stand-in results folder and its config (see the module docstring); reused when present."""
    from spinecohort.cohort.landmarks import DISCS
    from spinecohort.cohort.loading import Cohort, save_cohort
    from spinecohort.cohort.synthetic import generate_cohort
    from spinecohort.layout import Layout
    from spinecohort.mesh.hex_ssm import transfer_fields
    from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, build_template
    from spinecohort.ssm.model import build_ssm
    from spinecohort.ssm.procrustes import procrustes_align
    from spinecohort.store.zarr_store import grid_weights

    results, config = work / "results", work / "config.yaml"
    L = Layout(results)
    if Path(L.virtual_cohort_parquet).is_file() and config.is_file():
        return results, config
    for p in (L.ssm, L.template, L.cohort):
        Path(p).parent.mkdir(parents=True, exist_ok=True)
    c = generate_cohort(6, seed=1, resolution="default")
    ssm = build_ssm(procrustes_align(c.vertices).aligned)
    ssm.save(L.ssm)
    save_cohort(L.cohort, Cohort(c.ids, c.vertices, c.faces, c.landmarks, c.table))
    tpl = build_template(ssm.mean, c.faces, c.landmarks, TEMPLATE_RESOLUTIONS["coarse"])
    tpl.save(L.template)
    transfer_fields(tpl, tpl.nodes, ssm, c.landmarks, 5, "smooth", 1.0).save(L.hex_ssm)
    levels = [-3.0, -1.5, -0.5, 0.0, 0.5, 1.5, 3.0]
    w = grid_weights(5, levels)
    rng = np.random.default_rng(0)
    n = len(w)

    def lin(base, *coef, noise=1.0):
        return base + w[:, : len(coef)] @ np.array(coef) + rng.normal(0, noise, n)

    pt, ss = lin(20, 3, -2, 1), lin(35, -4, 3, 2)
    cols = {"model_id": [f"model_{i:05d}" for i in range(n)], **{f"w{k + 1}": w[:, k] for k in range(5)}}
    cols.update(PI=pt + ss, PT=pt, SS=ss, LL=lin(45, -6, 4, 2, 1), GT=lin(25, 3, 2), TPA=lin(20, 3, 1))
    cols["PI_minus_LL"] = cols["PI"] - cols["LL"]
    cols.update(TK_T1T12=lin(40, 5, -3), TK_T4T12=lin(35, 4, -3), TK_T5T12=lin(32, 4, -2), Cobb=np.abs(lin(5, 2, 0, 3)))
    cols.update(SVA_T1=lin(60, 15, 10, noise=5), SVA_C7est=lin(65, 15, 10, noise=5))
    cols.update({f"DH_{a}-{b}": np.abs(lin(8, 0.5, -0.3, 0.2, noise=0.3)) for a, b in DISCS})
    cols.update(GAP=rng.integers(0, 13, n).astype(float), GAP_category=rng.choice(["P", "MD", "SD"], n))
    cols.update(min_sj_after=rng.uniform(0.1, 0.5, n), invalid_after=np.zeros(n), repaired=rng.random(n) < 0.05)
    cols.update(distraction_mm=np.where(rng.random(n) < 0.1, rng.uniform(0, 3, n), 0.0))
    pd.DataFrame(cols).to_parquet(L.virtual_cohort_parquet, index=False)
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    cfg["results"] = str(results)
    cfg["grid"] = {"n_modes": 5, "levels": levels}
    config.write_text(yaml.safe_dump(cfg))
    return results, config


def median_ms(f, n=20) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def in_process(results: Path, config: Path) -> None:
    from spinecohort.web.app import Platform
    from spinecohort.web.data import filter_mask, open_data

    t0 = time.perf_counter()
    data = open_data(results=results, config=config)
    t1 = time.perf_counter()
    page = Platform(data)
    t2 = time.perf_counter()
    print(f"data load {t1 - t0:.2f} s, page construction {t2 - t1:.2f} s ({len(data.table):,} rows)")
    ranges = {"PI": (50.0, 60.0), "PT": (None, 25.0), "LL": (30.0, None)}
    n = int(filter_mask(data.table, ranges).sum())
    print(f"filter_mask, 3 ranges -> {n:,} rows: {median_ms(lambda: filter_mask(data.table, ranges)):.2f} ms (median)")
    s = page.state
    s.sort_by = [{"key": "PI", "order": "desc"}]

    def full():
        s.f_PI_lo = "50" if s.f_PI_lo != "50" else "51"
        page.apply_filter()

    print(f"page update (filter + sorted page + 9 histograms): {median_ms(full):.1f} ms (median)")
    all_rows = np.ones(len(data.table), bool)
    t = time.perf_counter()
    n_bytes = len(data.table_file(all_rows, "xlsx")[1])
    print(
        f"xlsx of the whole table ({len(data.table):,} rows, {data.table.shape[1]} columns): {time.perf_counter() - t:.1f} s, {n_bytes / 1e6:.1f} MB"
    )
    if data.workbook is not None:
        t = time.perf_counter()
        n_bytes = len(data.workbook_bytes())
        print(f"the prepared Descriptive_List.xlsx: {1e3 * (time.perf_counter() - t):.0f} ms, {n_bytes / 1e6:.1f} MB")
    w = np.array([1.0, -0.5, 0.3, 0.0, 2.0])[: data.hex_ssm.fields.shape[0]]
    ms = median_ms(lambda: page.scene.show(data.live_points(w)))
    print(f"live shape ({data.template.n_nodes:,} nodes): hex SSM formula + scene points {ms:.1f} ms (median)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _mem_mb(pid: int) -> dict[str, float]:
    """RSS, PSS (shared pages split between the processes that map them) and USS (private pages) in MB."""
    out = {}
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
        k, _, rest = line.partition(":")
        if k in ("Rss", "Pss", "Private_Clean", "Private_Dirty"):
            out[k] = int(rest.split()[0]) / 1024
    return {"rss": out["Rss"], "pss": out["Pss"], "uss": out["Private_Clean"] + out["Private_Dirty"]}


def _tree(pid: int) -> list[int]:
    """``pid`` and all its descendants (the launcher, its session starter and the sessions)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").iterdir():
            kids = (task / "children").read_text().split()
            todo += [int(k) for k in kids]
    return out


def _children(pid: int) -> list[int]:
    return [int(k) for task in Path(f"/proc/{pid}/task").iterdir() for k in (task / "children").read_text().split()]


def _sessions(server_pid: int) -> list[int]:
    """The session processes (children of the session starter, itself the launcher's child), oldest first."""
    pids = [g for c in _children(server_pid) for g in _children(c)]
    return sorted(pids, key=lambda p: Path(f"/proc/{p}").stat().st_ctime)


def in_browser(results: Path, config: Path, sessions: int, shots: Path | None, churn: bool) -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    from test_web_browser import _canvas_pixels, _drawn_share, _type, _wait, chrome

    port = _free_port()
    cmd = [sys.executable, "-m", "spinecohort.cli", "serve", "--port", str(port), "--max-sessions", str(sessions + 3)]
    cmd += ["--config", str(config), "--results", str(results)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    url = f"http://127.0.0.1:{port}/"
    drivers = []
    try:
        _wait(lambda: urllib.request.urlopen(url + "status", timeout=1), 120, "the server")
        print(f"start: first HTTP answer {time.perf_counter() - t0:.1f} s after `spinecohort serve`")
        base = sum(_mem_mb(p)["pss"] for p in _tree(proc.pid))
        print(f"memory with no session open (launcher, session starter, one spare session): PSS {base:.0f} MB")
        drv = chrome(size=(1600, 1000))
        drivers.append(drv)
        t1 = time.perf_counter()
        drv.get(url)
        _wait(lambda: _drawn_share(_canvas_pixels(drv)) > 0.02, 120, "a drawn 3D view")
        print(
            f"page + 3D view drawn {time.perf_counter() - t1:.1f} s after loading it "
            f"({time.perf_counter() - t0:.1f} s after start)"
        )
        n_all = drv.find_element("id", "match-count").text.split()[0]
        lat = []
        for lo, count in (("1000", "0"), ("", n_all)) * 3:  # nothing matches PI >= 1000 deg; '' = everything
            t = time.perf_counter()
            _type(drv, "f_PI_lo", lo)
            _wait(lambda: drv.find_element("id", "match-count").text.split()[0] == count, 10, "the count")
            lat.append(time.perf_counter() - t)
        print(
            f"filter in the browser (select-all, delete, type a bound -> new count): median {1e3 * np.median(lat):.0f} ms"
        )
        e2e, server_ms = [], []
        for w in (0.5, 1.0, 1.5, 2.0, 2.5):  # one state change each, as one slider step sends it
            time.sleep(1.5)
            before = _canvas_pixels(drv)
            t = time.perf_counter()
            drv.execute_script(f"window.trame.state.set('w_0', {w})")
            _wait(lambda: (np.abs(_canvas_pixels(drv) - before).sum(axis=2) > 30).mean() > 0.001, 10, "a change")
            e2e.append(time.perf_counter() - t)
            server_ms.append(drv.execute_script("return window.trame.state.get('live_ms')"))
        print(
            f"slider: server (sample + serialise + publish) median {np.median(server_ms):.0f} ms; "
            f"state change -> changed canvas median {1e3 * np.median(e2e):.0f} ms (polling canvas screenshots)"
        )
        for _ in range(sessions - 1):
            d = chrome(size=(1600, 1000))
            drivers.append(d)
            d.get(url)
            _wait(lambda d=d: _drawn_share(_canvas_pixels(d)) > 0.02, 120, "a drawn 3D view")
        time.sleep(3)
        pids = _tree(proc.pid)
        mem = {p: _mem_mb(p) for p in pids}
        total = sum(m["pss"] for m in mem.values())
        per = sorted(mem.items(), key=lambda kv: -kv[1]["pss"])
        print(f"{sessions} sessions open: {len(pids)} processes, total PSS {total:.0f} MB")
        for p, m in per:
            print(f"  pid {p}: RSS {m['rss']:.0f} MB, PSS {m['pss']:.0f} MB, private {m['uss']:.0f} MB")
        own = [mem[p] for p in _sessions(proc.pid)[:sessions]]  # the assigned ones (the newest is the spare)
        print(
            f"  per session process: PSS {np.mean([m['pss'] for m in own]):.0f} MB, "
            f"private {np.mean([m['uss'] for m in own]):.0f} MB (mean of {len(own)})"
        )
        for d in drivers[1:]:  # five software-WebGL browsers on a small machine would slow the pictures
            d.quit()
        drivers[1:] = []
        if shots:
            screenshots(url, shots)
        if churn:
            churn_memory(drv, proc.pid, yaml.safe_load(config.read_text())["grid"])
    finally:
        for d in drivers:
            d.quit()
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


def churn_memory(drv, server_pid: int, grid: dict, n_select: int = 100, n_zip: int = 10) -> None:
    """Memory of the first session over ``n_select`` model selections and ``n_zip`` zips of 4 decks."""
    sys.path.insert(0, str(ROOT / "tests"))
    from spinecohort.store.zarr_store import n_models
    from test_web_browser import _type, _wait

    pid = _sessions(server_pid)[0]
    start = _mem_mb(pid)
    rng = np.random.default_rng(0)
    n = n_models(grid["n_modes"], grid["levels"])
    t0 = time.perf_counter()
    for k, i in enumerate(rng.integers(0, n, n_select)):
        name = f"model_{i:05d}"
        _type(drv, "model_input", name)
        drv.find_element("id", "show").click()
        _wait(lambda name=name: drv.find_element("id", "shown").text.startswith(name), 30, name)
        if k in (0, n_select // 2, n_select - 1):
            print(f"  after {k + 1} selections: session RSS {_mem_mb(pid)['rss']:.0f} MB")
    print(f"{n_select} selections in {time.perf_counter() - t0:.0f} s")
    _type(drv, "f_other", "w1 3:; w2 3:; w3 3:; w4 3:; w5 0:")
    _wait(lambda: drv.find_element("id", "match-count").text.split()[0] == "4", 20, "4 models")
    for k in range(n_zip):
        t = time.perf_counter()
        drv.execute_script(
            "window.__zip = null; window.trame.trigger('download_zip', []).then((b) => window.__zip = b)"
        )
        _wait(lambda: drv.execute_script("return window.__zip !== null"), 300, "the zip")
        print(f"  zip {k + 1} (4 decks): {time.perf_counter() - t:.1f} s, session RSS {_mem_mb(pid)['rss']:.0f} MB")
    end = _mem_mb(pid)
    print(f"session memory over {n_select} selections + {n_zip} zips: RSS {start['rss']:.0f} -> {end['rss']:.0f} MB")


def screenshots(url: str, out: Path) -> None:
    """The page at 1366 x 768 and 1920 x 1080: a patient's numbers found, a filter, a model on screen."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_web_browser import _show, _type, _wait, chrome, open_page

    out.mkdir(parents=True, exist_ok=True)
    for w, h in ((1366, 768), (1920, 1080)):
        d = chrome(size=(w, h))
        try:
            open_page(d, url)
            _type(d, "pat_PI", "60")
            _type(d, "pat_PT", "25")
            d.find_element("id", "find").click()
            _wait(lambda d=d: "d = " in d.find_element("id", "nearest").text, 60, "nearest")
            _type(d, "f_PI_lo", "55")
            _type(d, "f_LL_hi", "50")
            _show(d, "model_08403")
            time.sleep(4)
            d.save_screenshot(str(out / f"platform-{w}.png"))
            print(f"screenshot: {out / f'platform-{w}.png'}")
        finally:
            d.quit()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "spinecohort-bench-web")
    ap.add_argument("--results", type=Path)
    ap.add_argument("--config", type=Path)
    ap.add_argument("--sessions", type=int, default=5)
    ap.add_argument("--screenshots", type=Path, help="folder for platform-1366.png and platform-1920.png")
    ap.add_argument("--churn", action="store_true", help="memory over 100 selections and 10 zips")
    ap.add_argument("--no-browser", action="store_true")
    a = ap.parse_args()
    if a.results:
        results, config = a.results, a.config or ROOT / "config" / "config.yaml"
    else:
        t0 = time.perf_counter()
        results, config = make_results(a.work)
        print(f"stand-in results in {a.work} ({time.perf_counter() - t0:.0f} s)")
    in_process(results, config)
    if not a.no_browser and Path("/usr/bin/chromium").exists():
        in_browser(results, config, a.sessions, a.screenshots, a.churn)


if __name__ == "__main__":
    main()
