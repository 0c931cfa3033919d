"""A published release read over HTTP without downloading it: the store zip in place (range requests), the
small files it needs fetched once into a cache folder, models cached on disk up to a size bound.

A release URL is either the bag served as a folder (``URL/data/cohort.zarr.zip``, ``URL/data/model_inputs/…``)
or the flat deposit (``URL/cohort.zarr.zip`` and ``URL/bag.zip``, whose members are read by range as well),
or the store zip's own URL (then its folder is the release).  ``spinecohort export --release URL`` and
``spinecohort serve --release URL`` use :class:`RemoteRelease`.
"""

from __future__ import annotations

import hashlib
import json
import os
import urllib.parse
from pathlib import Path

import numpy as np

from spinecohort.release.names import BAG_ZIP, MODEL_INPUTS, RELEASE_JSON, STORE_ZIP, ReleaseError, safe_relpath
from spinecohort.release.reader import is_url, open_store, probe_url, read_model_from, surface_vertex

#: read-ahead, bytes, of the fsspec file that reads members of the deposit's bag.zip (small files)
BAG_BLOCK_BYTES = 1 << 20

#: the files of ``data/`` that export and the platform need besides the store (fetched once, then cached)
PLATFORM_FILES = (
    "virtual_cohort.csv",
    RELEASE_JSON,
    f"{MODEL_INPUTS}/ssm.npz",
    f"{MODEL_INPUTS}/hex_ssm.npz",
    f"{MODEL_INPUTS}/template.npz",
    f"{MODEL_INPUTS}/faces.npy",
)
DEFAULT_CACHE_MB = 500.0


def default_cache_dir(url: str) -> Path:
    """``$XDG_CACHE_HOME/spinecohort/<16 hex digits of the URL's sha256>`` (default ``~/.cache``)."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "spinecohort" / hashlib.sha256(url.encode()).hexdigest()[:16]


def _join(base: str, name: str) -> str:
    return base.rstrip("/") + "/" + urllib.parse.quote(name)


class RemoteRelease:
    """A release at an http(s) URL, read on demand.

    url: the bag's URL, the deposit's (the folder holding ``cohort.zarr.zip``), or the store zip's own URL.
    cache_dir: where fetched files and decoded models go (default :func:`default_cache_dir`); cache_mb:
    the bound on the cached models (least recently used dropped first; fetched files are not counted).
    """

    def __init__(self, url: str, cache_dir=None, cache_mb: float = DEFAULT_CACHE_MB):
        if not is_url(url):
            raise ReleaseError(f"{url!r} is not an http(s) URL of a release")
        self.url = url
        self.cache = Path(cache_dir) if cache_dir is not None else default_cache_dir(url)
        self.cache_bytes = int(cache_mb * 1e6)
        self.store_url, self._files = self._locate(url)
        self._root = None
        self._skin = None
        self._bag = None

    def _locate(self, url: str) -> tuple[str, str]:
        """(store zip URL, how data/ files are read: "bag" URL/data/<rel>, or "zip" members of bag.zip)."""
        base = url.split("?", 1)[0]
        if base.endswith(STORE_ZIP):
            folder = base[: -len(STORE_ZIP)]
            layout = "bag" if folder.rstrip("/").endswith("/data") else "zip"
            self.base = folder.rstrip("/").removesuffix("/data") if layout == "bag" else folder
            return url, layout
        self.base = base
        try:
            probe_url(_join(base, f"data/{STORE_ZIP}"))
            return _join(base, f"data/{STORE_ZIP}"), "bag"
        except ReleaseError as first:
            if "ignores HTTP Range" in str(first):
                raise
            try:
                probe_url(_join(base, STORE_ZIP))
            except ReleaseError as second:
                raise ReleaseError(
                    f"{url}: no release there: neither the bag (data/{STORE_ZIP}: {first}) nor the deposit "
                    f"({STORE_ZIP}: {second})"
                ) from None
            return _join(base, STORE_ZIP), "zip"

    # ---------------------------------------------------------------------------------- files
    @property
    def root(self):
        """The store, a read-only zarr group over HTTP (opened on first use)."""
        if self._root is None:
            self._root = open_store(self.store_url)
            self._skin = surface_vertex(self._root)
        return self._root

    def file(self, rel: str) -> Path:
        """Local path of ``data/<rel>`` of the release, fetched once into the cache."""
        out = self.cache / "data" / safe_relpath(rel, "release file")
        if out.is_file():
            return out
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(out.name + f".{os.getpid()}.partial")
        if self._files == "bag":
            import fsspec

            url = _join(self.base, f"data/{rel}")
            try:
                with fsspec.open(url, "rb", block_size=0) as fin, open(tmp, "wb") as fout:
                    while block := fin.read(1 << 20):
                        fout.write(block)
            except FileNotFoundError:
                tmp.unlink(missing_ok=True)
                raise ReleaseError(f"{url}: not found (HTTP 404); is {self.base} a spinecohort release?") from None
        else:
            zfs = self._bag_zip()
            member = f"data/{rel}"
            if not zfs.exists(member):
                raise ReleaseError(f"{_join(self.base, BAG_ZIP)}: has no member {member}")
            with zfs.open(member, "rb") as fin, open(tmp, "wb") as fout:
                while block := fin.read(1 << 20):
                    fout.write(block)
        os.replace(tmp, out)
        return out

    def _bag_zip(self):
        if self._bag is None:
            import fsspec
            from fsspec.implementations.zip import ZipFileSystem

            url = _join(self.base, BAG_ZIP)
            size = probe_url(url)
            http = fsspec.filesystem("http", block_size=BAG_BLOCK_BYTES, skip_instance_cache=True)
            self._bag = ZipFileSystem(fo=http.open(url, "rb", size=size))
        return self._bag

    def info(self) -> dict:
        """release.json: grid, hex type, ``fe`` materials, counts."""
        return json.loads(self.file(RELEASE_JSON).read_text())

    def platform_folder(self) -> Path:
        """A bag-shaped folder (``<cache>/data/…``) holding the table and the model inputs, fetched once:
        what ``Sources.from_release`` reads.  The store stays remote (:meth:`hex_points`)."""
        for rel in PLATFORM_FILES:
            self.file(rel)
        return self.cache

    # --------------------------------------------------------------------------------- models
    def model(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(tri (n_tri, 3), hex (n_hex, 3)) float32 mm of model ``i``: from the disk cache, else read over
        HTTP (one chunk per point array) and cached, dropping the least recently used beyond the bound."""
        path = self.cache / "models" / f"model_{int(i):05d}.npz"
        if path.is_file():
            os.utime(path)  # most recently used
            with np.load(path, allow_pickle=False) as z:
                return z["tri"], z["hex"]
        tri, hexa = read_model_from(self.root, int(i), self._skin)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.partial.npz")
        np.savez(tmp, tri=tri, hex=hexa)
        os.replace(tmp, path)
        self._evict(keep=path)
        return tri, hexa

    def virtual_model(self, model):
        """(VirtualModel of the stored coordinates, HexTemplate, release.json) of ``model`` (``model_08403`` or
        8403): what ``write_model`` needs to write its deck, STL or VTU, with the release's hex type and
        ``fe`` materials."""
        from spinecohort.fe.models import VirtualModel, parse_model_id
        from spinecohort.mesh.template import HexTemplate
        from spinecohort.store.zarr_store import weights_of

        info = self.info()
        i = parse_model_id(model, info["n_modes"], info["levels"])
        tri, hexa = self.model(i)
        template = HexTemplate.load(self.file(f"{MODEL_INPUTS}/template.npz"))
        w = np.asarray(weights_of(i, info["n_modes"], info["levels"]), float)
        report = {"source": f"stored coordinates of {self.store_url}"}
        return VirtualModel(i, w, np.asarray(tri, float), np.asarray(hexa, float), report), template, info

    def hex_points(self, i: int) -> np.ndarray:
        """The hex model's nodes (n_hex_nodes, 3) float mm of model ``i`` (the stored coordinates)."""
        return np.asarray(self.model(i)[1], float)

    def _evict(self, keep: Path) -> None:
        files = sorted((self.cache / "models").glob("model_*.npz"), key=lambda p: p.stat().st_mtime, reverse=True)
        total = 0
        for p in files:
            total += p.stat().st_size
            if total > self.cache_bytes and p != keep:
                p.unlink(missing_ok=True)


def platform_model_points(data, remote: RemoteRelease):
    """``data.model_points`` for a platform serving ``remote``: grid models (``model_NNNNN``) are the
    release's stored coordinates read on demand (:meth:`RemoteRelease.hex_points`), anything else goes
    to the platform's own ``model_points``."""
    own = data.model_points

    def model_points(name: str) -> np.ndarray:
        name = data.check_id(name)
        if name.startswith("model_"):
            return remote.hex_points(int(name[6:]))
        return own(name)

    return model_points
