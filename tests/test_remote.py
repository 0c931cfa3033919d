"""The release read over HTTP without downloading it (spinecohort.release.reader, .remote), against a real
nginx that this module starts on 127.0.0.1 and that serves the test config's release bag: the model read
equals the local store's, the bytes nginx sends for it (its access log) stay within twice the model's own
compressed bytes plus the shard indexes, a second implementation (tensorstore) reads the same model, the
data README's lines work as printed, `export`/`serve --release URL` use it, and a wrong URL, a truncated
zip and a server that ignores Range each fail with a message that says so."""

import json
import os
import re
import shutil
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest

from spinecohort.cli import main
from spinecohort.release import ReleaseError, open_store, read_model_from, zip_references
from spinecohort.release.nginx import LocalServer
from spinecohort.release.remote import RemoteRelease, platform_model_points
from spinecohort.store.zarr_store import read_model

NGINX = shutil.which("nginx") or ("/usr/sbin/nginx" if Path("/usr/sbin/nginx").exists() else None)
if NGINX is None and os.geteuid() != 0:
    pytest.skip(
        "nginx is not installed and this user cannot install it (scripts/install_system_deps.sh, as root)",
        allow_module_level=True,
    )
MODEL = 13  # shard 1 of the test store (3 shards of 9 models)


@pytest.fixture(scope="module")
def release(test_run):
    if NGINX is None:  # root: the install script would have put it there; do not skip silently
        pytest.fail("nginx is missing: run scripts/install_system_deps.sh (installs nginx-light)")
    return test_run / "results" / "release"


@pytest.fixture(scope="module")
def server(release, tmp_path_factory):
    with LocalServer(release, tmp_path_factory.mktemp("nginx")) as srv:
        yield srv


def _shard_costs(zip_path: Path, model: int) -> dict:
    """From the local zip, independently of any HTTP reader: per point array, the bytes of the inner chunk
    holding ``model``, that chunk's models, and the shard index (16 B per chunk + its 4-byte crc32c)."""
    refs = zip_references(zip_path)["refs"]
    data = zip_path.read_bytes()
    with zipfile.ZipFile(zip_path) as zf:
        attrs = json.loads(zf.read("zarr.json"))["attributes"]
    shard, row = divmod(model, attrs["shard_models"])
    n_chunks = attrs["shard_models"] // attrs["chunk_models"]
    out = {}
    for name in ("tri/points", "hex/volume_points"):
        _, off, size = refs[f"{name}/c/{shard}/0/0"]
        index = np.frombuffer(data[off + size - 16 * n_chunks - 4 : off + size - 4], "<u8").reshape(-1, 2)
        out[name] = {
            "chunk": int(index[row // attrs["chunk_models"], 1]),
            "models": attrs["chunk_models"],
            "index": 16 * n_chunks + 4,
        }
    return out


def test_one_model_over_http_equals_the_store_and_costs_its_own_bytes(release, server, test_run):
    root = open_store(f"{server.url}/data/cohort.zarr.zip")
    skin = root["hex/surface_vertex"][:]
    server.clear_log()
    tri, hexa = read_model_from(root, MODEL, skin)
    local_tri, local_hex = read_model(test_run / "results" / "cohort.zarr", MODEL)
    assert np.array_equal(tri, local_tri) and np.array_equal(hexa, local_hex)
    sent = server.requests()
    assert {r.status for r in sent} == {206}  # ranges only: nothing sent whole
    costs = _shard_costs(release / "data" / "cohort.zarr.zip", MODEL)
    own = sum(c["chunk"] / c["models"] for c in costs.values())  # the model's own compressed bytes
    index = sum(c["index"] for c in costs.values())
    # the goal: at most twice the model's own bytes plus the shard indexes; with one model per chunk
    # zarr fetches exactly each array's index and the model's chunk (4 range requests, no read-ahead)
    assert sum(r.nbytes for r in sent) <= 2 * own + index
    assert sorted(r.nbytes for r in sent) == sorted(
        [c["index"] for c in costs.values()] + [c["chunk"] for c in costs.values()]
    )


def test_tensorstore_reads_the_same_model_over_http(server, test_run):
    """A second Zarr v3 implementation, through its zip kvstore over its HTTP kvstore, decodes the same
    float32 values (tensorstore's zip driver reads whole members: fine here, GBs on the default store)."""
    ts = pytest.importorskip("tensorstore")
    url = f"{server.url}/data/cohort.zarr.zip"
    local_tri, local_hex = read_model(test_run / "results" / "cohort.zarr", MODEL)
    got = {}
    for name in ("tri/points", "hex/volume_points"):
        spec = {"driver": "zarr3", "kvstore": {"driver": "zip", "base": url, "path": f"{name}/"}}
        got[name] = ts.open(spec, read=True).result()[MODEL].read().result()
    assert np.array_equal(got["tri/points"], local_tri)
    assert np.array_equal(got["hex/volume_points"], local_hex[: len(got["hex/volume_points"])])


def test_the_readme_lines_read_the_model_from_the_server(release, server, test_run):
    """The HTTP code block of the generated data/README.md, run as printed with ``url`` set."""
    text = (release / "data" / "README.md").read_text()
    block = re.search(r"Or straight from the record.*?```python\n(.*?)```", text, re.S).group(1)
    assert len([ln for ln in block.splitlines() if ln.strip()]) == 3
    scope = {"url": f"{server.url}/data/cohort.zarr.zip"}
    server.clear_log()
    exec(block, scope)
    # the zip's bytes sent: the two shard indexes and the model's two chunks (the references are fetched once)
    sent = [r for r in server.requests() if r.uri.endswith(".zip")]
    costs = _shard_costs(
        release / "data" / "cohort.zarr.zip",
        json.loads((release / "data" / "model_inputs" / "release.json").read_text())["mean_model_id"],
    )
    assert {r.status for r in sent} == {206}
    assert sum(r.nbytes for r in sent) == sum(c["index"] + c["chunk"] for c in costs.values())
    mean = json.loads((release / "data" / "model_inputs" / "release.json").read_text())["mean_model_id"]
    local_tri, local_hex = read_model(test_run / "results" / "cohort.zarr", mean)
    assert np.array_equal(scope["tri_mm"], local_tri)
    assert np.array_equal(scope["vol_mm"], local_hex[: len(scope["vol_mm"])])


def test_export_from_the_release_url_writes_the_stored_model(server, test_run, tmp_path, capsys):
    from spinecohort.fe.export import read_deck_points
    from spinecohort.mesh.template import HexTemplate

    out = tmp_path / "m.inp"
    args = ["export", f"model_{MODEL:05d}", "--release", server.url, "--out", str(out), "--cache-dir", str(tmp_path)]
    assert main(args) == 0
    assert "stored coordinates of" in capsys.readouterr().out
    template = HexTemplate.load(test_run / "results" / "template" / "template.npz")
    _, local_hex = read_model(test_run / "results" / "cohort.zarr", MODEL)
    # the deck prints mm with 6 decimals: the stored float32 values to within half a micrometre
    assert np.abs(read_deck_points(out, template) - local_hex).max() <= 5e-7 + 1e-9


def test_serve_hook_reads_models_on_demand_within_the_cache_bound(server, test_run, tmp_path):
    from spinecohort.web.data import open_data

    remote = RemoteRelease(server.url, cache_dir=tmp_path, cache_mb=0.5)  # ~ one cached model of the test grid
    data = open_data(release=remote.platform_folder())
    data.model_points = platform_model_points(data, remote)
    assert len(data.table) >= 27
    for k in (MODEL, 0, MODEL):
        assert np.array_equal(
            data.model_points(f"model_{k:05d}"), read_model(test_run / "results" / "cohort.zarr", k)[1]
        )
    cached = sorted(p.name for p in (tmp_path / "models").iterdir())
    assert cached == [f"model_{MODEL:05d}.npz"]  # the bound keeps the most recently used model only
    server.clear_log()
    data.model_points(f"model_{MODEL:05d}")
    assert server.requests() == []  # served from the disk cache


def test_a_wrong_url_names_what_is_missing(server):
    with pytest.raises(ReleaseError, match=r"nope\.zip: not found \(HTTP 404\)"):
        open_store(f"{server.url}/data/nope.zip")
    with pytest.raises(ReleaseError, match=r"no release there: neither the bag .* nor the deposit"):
        RemoteRelease(f"{server.url}/elsewhere/", cache_dir="/nonexistent")
    with pytest.raises(ReleaseError, match=r"cannot be reached"):
        open_store("http://127.0.0.1:9/cohort.zarr.zip")  # the discard port: nothing listens


def test_a_truncated_zip_is_named(release, tmp_path):
    site = tmp_path / "site"
    shutil.copytree(release, site)
    store = site / "data" / "cohort.zarr.zip"
    full = store.stat().st_size
    with open(store, "r+b") as f:
        f.truncate(full // 2)
    with LocalServer(site, tmp_path / "nginx") as srv:
        with pytest.raises(ReleaseError, match=rf"{full // 2} bytes on the server, its references expect {full}"):
            open_store(f"{srv.url}/data/cohort.zarr.zip")


def test_a_server_that_ignores_range_is_named(release, tmp_path):
    with LocalServer(release, tmp_path / "nginx", max_ranges=0) as srv:
        url = f"{srv.url}/data/cohort.zarr.zip"
        # the premise: with max_ranges 0 nginx answers a range with the whole file (200), as such servers do
        req = urllib.request.Request(url, headers={"Range": "bytes=0-0"})
        with urllib.request.urlopen(req) as r:
            assert (
                r.status == 200
                and int(r.headers["Content-Length"]) == (release / "data" / "cohort.zarr.zip").stat().st_size
            )
        with pytest.raises(ReleaseError, match=r"the server ignores HTTP Range requests"):
            open_store(url)
        with pytest.raises(ReleaseError, match=r"ignores HTTP Range"):
            RemoteRelease(srv.url, cache_dir=tmp_path / "cache")


def test_the_flat_deposit_reads_over_http_as_the_bag_does(release, test_run, tmp_path):
    """The deposit's four files served flat (as a repository serves a record): the store read in place, the
    model inputs read as members of bag.zip by range, from the folder's URL or the store zip's own URL."""
    from spinecohort.release import make_deposit

    make_deposit(release, tmp_path / "record")
    _, local_hex = read_model(test_run / "results" / "cohort.zarr", MODEL)
    with LocalServer(tmp_path / "record", tmp_path / "nginx") as srv:
        for url in (srv.url, f"{srv.url}/cohort.zarr.zip"):
            remote = RemoteRelease(url, cache_dir=tmp_path / "cache" / str(len(url)))
            vm, template, info = remote.virtual_model(f"model_{MODEL:05d}")
            assert np.array_equal(vm.hex_points, local_hex) and template.n_nodes == len(local_hex)
            assert info["n_models"] == 27 and info["store"] == "cohort.zarr.zip"
        # bag.zip is read by range too: its members, not the whole zip
        sent = [r for r in srv.requests() if r.uri.endswith("bag.zip")]
        assert all(r.status == 206 for r in sent)
        assert sum(r.nbytes for r in sent) < (tmp_path / "record" / "bag.zip").stat().st_size


def test_serve_release_url_draws_a_model_fetched_by_its_browser_session(server, test_run, tmp_path):
    """`spinecohort serve --release URL` end to end: each browser session is a process forked from the
    server, and the model it shows is read over HTTP by that process (nginx serves its byte ranges)."""
    import signal
    import subprocess
    import sys

    from test_web import wait_for_server
    from test_web_browser import CHROMEDRIVER, CHROMIUM, _free_port, _show, chrome, open_page

    if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
        pytest.fail("Chromium is missing: run scripts/install_system_deps.sh")
    port = _free_port()
    log = tmp_path / "serve.log"
    cmd = [sys.executable, "-m", "spinecohort.cli", "serve", "--port", str(port), "--release", server.url]
    cmd += ["--cache-dir", str(tmp_path / "cache"), "--max-sessions", "2"]
    proc = subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
    drv = None
    try:
        wait_for_server(f"http://127.0.0.1:{port}/status", proc, log)
        server.clear_log()
        drv = open_page(chrome(tmp_path / "downloads"), f"http://127.0.0.1:{port}/", log)
        _show(drv, f"model_{MODEL:05d}")
        zip_ranges = [r for r in server.requests() if r.uri.endswith("cohort.zarr.zip")]
        assert zip_ranges and all(r.status == 206 for r in zip_ranges), zip_ranges
        cached = np.load(tmp_path / "cache" / "models" / f"model_{MODEL:05d}.npz")  # what the session drew
        assert np.array_equal(cached["hex"], read_model(test_run / "results" / "cohort.zarr", MODEL)[1])
    finally:
        if drv is not None:
            drv.quit()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=20)
