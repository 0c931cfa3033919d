"""Open the cohort store wherever it is (a folder, a local ``cohort.zarr.zip``, or that zip at an HTTP(S)
URL, read in place with range requests) and read a model with the store's public functions.

Over HTTP the reader takes the zip's references (``cohort.zarr.refs.json``, beside the zip: each member's
offset and size in the zip, the metadata inlined) and hands them to fsspec's ReferenceFileSystem: zarr then
fetches a shard's index (a suffix of its member) and one inner chunk per point array, each an exact byte
range of the zip; nothing is read ahead, nothing downloaded whole.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from spinecohort.release.names import ReleaseError


def is_url(source) -> bool:
    """True for an ``http://`` or ``https://`` URL (a release or its store read over HTTP)."""
    return isinstance(source, str) and source.lower().startswith(("http://", "https://"))


def probe_url(url: str, timeout_s: float = 30.0) -> int:
    """Size in bytes of the file at ``url`` after checking that its server honours Range requests (a
    1-byte range must come back as 206 Partial Content).  Raises ReleaseError naming the URL and the
    problem: not found, not reachable, or ranges ignored (a reader would then download whole files)."""
    import urllib.error
    import urllib.request

    req = urllib.request.Request(url, headers={"Range": "bytes=0-0", "User-Agent": "spinecohort"})
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as r:  # headers only: the body is not read
            status, content_range = r.status, r.headers.get("Content-Range", "")
    except urllib.error.HTTPError as exc:
        what = "not found" if exc.code in (404, 410) else f"refused ({exc.reason})"
        raise ReleaseError(f"{url}: {what} (HTTP {exc.code}); check the release URL") from None
    except (urllib.error.URLError, OSError) as exc:
        raise ReleaseError(f"{url}: cannot be reached ({getattr(exc, 'reason', exc)})") from None
    if status != 206 or "/" not in content_range:
        raise ReleaseError(
            f"{url}: the server ignores HTTP Range requests (answered a 1-byte range with HTTP {status} and the "
            "whole file); reading one model would download the whole store. Serve it from a server that "
            "honours ranges (Zenodo, S3, nginx, Apache), or download the file and open it locally"
        )
    total = content_range.rsplit("/", 1)[1]
    return int(total) if total.isdigit() else -1


def _get_json(url: str, timeout_s: float = 60.0) -> dict:
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(
            urllib.request.Request(url, headers={"User-Agent": "spinecohort"}), timeout=timeout_s
        ) as r:
            return json.loads(r.read())
    except urllib.error.HTTPError as exc:
        raise ReleaseError(f"{url}: HTTP {exc.code} ({exc.reason}); the store zip's references are needed") from None
    except (urllib.error.URLError, OSError) as exc:
        raise ReleaseError(f"{url}: cannot be reached ({getattr(exc, 'reason', exc)})") from None
    except json.JSONDecodeError as exc:
        raise ReleaseError(f"{url}: not JSON ({exc}); not the store zip's references") from None


def refs_url(zip_url: str) -> str:
    """The references' URL beside a store zip's: ``…/cohort.zarr.zip`` -> ``…/cohort.zarr.refs.json``."""
    base, _, query = zip_url.partition("?")
    return base.removesuffix(".zip") + ".refs.json" + (f"?{query}" if query else "")


def _http_zip_store(url: str, refs: str | None):
    from fsspec.implementations.reference import ReferenceFileSystem
    from zarr.storage import FsspecStore

    size = probe_url(url)
    refs = _get_json(refs or refs_url(url))
    want = refs.get("zip_bytes")
    if not isinstance(refs.get("refs"), dict):
        raise ReleaseError(f"{url}: its references hold no 'refs' table; not a spinecohort store zip")
    if want is not None and size != want:
        raise ReleaseError(
            f"{url}: {size} bytes on the server, its references expect {want} (the zip is truncated or replaced)"
        )
    fs = ReferenceFileSystem(
        fo={"version": 1, "refs": refs["refs"]},
        target=url,
        remote_protocol=url.split(":", 1)[0].lower(),
        remote_options={"asynchronous": True},
        asynchronous=True,
    )
    return FsspecStore(fs, read_only=True, path="")


def open_store(source, *, refs: str | None = None):
    """The store as a read-only zarr group.  source: a store folder, a local ``cohort.zarr.zip``, or an
    http(s) URL of a ``cohort.zarr.zip`` (refs: its references' URL; default beside it, :func:`refs_url`).
    Raises ReleaseError naming the source when it cannot be opened or is not a cohort store of this
    version."""
    import zarr
    from zarr.storage import ZipStore

    if is_url(source):
        store = _http_zip_store(source, refs)
    elif Path(source).is_file():
        store = ZipStore(Path(source), mode="r", read_only=True)
    elif Path(source).is_dir():
        store = str(source)
    else:
        raise ReleaseError(f"{source}: no such store (a folder, a cohort.zarr.zip, or an http(s) URL of one)")
    try:
        root = zarr.open_group(store, mode="r")
    except (FileNotFoundError, KeyError, json.JSONDecodeError, zarr.errors.GroupNotFoundError) as exc:
        raise ReleaseError(f"{source}: not a Zarr v3 store ({type(exc).__name__}: {exc})") from None
    store_meta(root, source)
    return root


def store_meta(root, source="store") -> dict:
    """The store's attributes after checking its format (:data:`spinecohort.store.zarr_store.STORE_FORMAT`)."""
    from spinecohort.store.zarr_store import STORE_FORMAT

    meta = dict(root.attrs)
    if meta.get("format") != STORE_FORMAT:
        raise ReleaseError(
            f"{source}: store format {meta.get('format')!r}, this version reads {STORE_FORMAT!r}; "
            "use the spinecohort version that wrote the release"
        )
    return meta


def surface_vertex(root) -> np.ndarray:
    """The tri vertex of each hex skin node (the same for every model: read it once per open store)."""
    from spinecohort.store.zarr_store import SURFACE_VERTEX

    return root[SURFACE_VERTEX][:]


def read_model_from(root, i: int, skin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(tri (n_tri_nodes, 3), hex (n_hex_nodes, 3)) float32 mm of model ``i`` of an open store: the hex
    model's volume nodes, then its skin nodes taken from the tri vertices (``hex_model_points``).
    skin: :func:`surface_vertex` of the store, if already read."""
    from spinecohort.store.zarr_store import hex_model_points

    n = int(root.attrs["n_models"])
    if not 0 <= int(i) < n:
        raise ReleaseError(f"model {i} out of range [0, {n})")
    tri = root["tri/points"][int(i)]
    skin = surface_vertex(root) if skin is None else skin
    return tri, hex_model_points(root["hex/volume_points"][int(i)], tri, skin)
