"""The cohort store's format: its Zarr v3 layout, encoding and metadata, created empty and read back.

Layout (one store, written shard by shard by independent jobs)::

    weights            (n_models, n_modes)           float64, SD units; one chunk per shard (zstd)
    tri/points         (n_models, n_tri_nodes, 3)    float32 mm; chunk_models models per inner chunk,
                                                     shard_models per shard
    hex/volume_points  (n_models, n_volume_nodes, 3) float32 mm: the hex model's own nodes (vertebral bodies,
                                                     endplates, discs); same chunking
    hex/surface_vertex (n_surface_nodes,)            int32: the tri vertex each remaining hex-model node is
                                                     (posterior elements, sacrum, pelvis, femoral heads: S3 skins
                                                     on the triangulated surface; the same for every model)
    checksums/shard_NNNNN                            per-shard group whose attributes hold the crc32c and size of
                                                     the shard's stored objects; written last, atomically: the
                                                     completion mark

The hex model's nodes (node k = node k+1 of "Mean_Model (Template).inp") are the volume nodes followed by
those tri vertices (:func:`hex_model_points`)::

    hex = np.concatenate([z["hex/volume_points"][i], z["tri/points"][i][z["hex/surface_vertex"][:]]])

so the 52,772 surface nodes are stored once, not twice (docs/reference/store-format.md).  Model IDs and
shards: :mod:`spinecohort.store.grid`.

Encoding (chosen by measurement, docs/explanation/performance.md): every array uses only codecs of the Zarr
v3 core specification, so any conforming reader (zarr-python, tensorstore, zarrs, zarr.js, Zarr.jl) decodes
``z["tri/points"][i]`` and ``z["hex/volume_points"][i]`` to float32 millimetres.  Coordinates are rounded to
multiples of 2^-10 mm (exact in float32 for |x| < 16 m, so the stored value *is* the rounded one: error <=
2^-11 mm = 0.49 um), an inner chunk holds the ``chunk_models`` models along the last mode, and the
``transpose`` codec stores it coordinate-major with the model axis innermost (x of node 0 of the 7 models,
x of node 1, ...), where neighbouring values share their high bits; ``blosc`` (bitshuffle, zstd level 3,
blocks of 8,192 nodes x 7 models) then packs the bit planes.  Sharding codec: one shard object per array
per shard, index at the end with crc32c (written by :mod:`spinecohort.store.writer`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import zarr
from numcodecs import Blosc
from zarr.codecs import BloscCodec, TransposeCodec, ZstdCodec

from spinecohort.store.grid import (
    DEFAULT_LEVELS,
    DEFAULT_N_MODES,
    DEFAULT_SHARD_MODELS,
    _levels_array,
    n_models,
    n_shards,
    shard_range,
)

#: the finest quantum of the encodings: "float32-q10" stores multiples of 2^-10 mm (0.98 um; rounding error
#: <= 0.49 um), "float32-q9" of 2^-9 mm (error <= 0.98 um); it bounds the coordinates float32 holds exactly
QUANTUM_EXP = 10
ENCODINGS = ("float32-q10", "float32-q9", "float32")
#: the per-shard coordinate arrays
POINT_ARRAYS = ("tri/points", "hex/volume_points")
SURFACE_VERTEX = "hex/surface_vertex"
#: the layout this module writes and reads; a store of another format is refused (``_open_meta``)
STORE_FORMAT = "spinecohort.cohort-store/4"
_FORMAT_PREFIX = "spinecohort.cohort-store/"
#: blosc inside each inner chunk: bitshuffle, clevel 2 (blosc's zstd level 3) on blocks of 224 KiB = 8,192
#: nodes x 7 models x 4 B (docs/explanation/performance.md: 3.6 % fewer bytes than clevel 1 on 1 MiB blocks
#: at ~1.8x its encode CPU; 1 MiB and 4 MiB blocks compress worse, blosc's clevel 3 is no better)
BLOSC_CLEVEL = 2
BLOSC_BLOCK_BYTES = 224 << 10
#: transpose of an inner chunk (models, nodes, xyz) -> stored (xyz, nodes, models)
CHUNK_ORDER = (2, 1, 0)
_CHECKSUM_DIR = "checksums"
_EMPTY = 2**64 - 1  # the sharding index's marker of a chunk that is not stored
#: fault injection for the kill-and-resume test: a process with this variable set to a shard number is
#: SIGKILLed by ``ShardWriter.close`` after that shard's first array object is in place (a node failure)
FAULT_KILL_ENV = "SPINECOHORT_FAULT_KILL_SHARD"
# float32 spacing relative to magnitude: one rounding contributes at most half an ulp
_F32_HALF_ULP_REL = 2.0**-24


class StoreVersionError(ValueError):
    """The store was written by another version of spinecohort (its ``format`` attribute differs)."""


def quantum_scale(encoding: str) -> float:
    """2^k for "float32-qk" (coordinates stored as multiples of 2^-k mm), 0.0 for "float32" (no rounding)."""
    if encoding not in ENCODINGS:
        raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")
    return 0.0 if encoding == "float32" else float(2 ** int(encoding.split("-q")[1]))


def quantize_mm(x: np.ndarray, encoding: str = "float32-q10") -> np.ndarray:
    """Coordinates (mm, any float dtype) as stored: float32 multiples of 2^-k mm ("float32-qk", k = 10 or 9) or
    the nearest float32 ("float32").  Rounding happens in float64, so it is exact: |x| * 2^k < 2^24."""
    scale = quantum_scale(encoding)
    if not scale:
        return np.asarray(x, dtype=np.float32)
    return (np.rint(np.asarray(x, dtype=np.float64) * scale) / scale).astype(np.float32)


def _blosc_codecs(clevel: int) -> tuple[BloscCodec, Blosc]:
    """The core-spec blosc codec of the point arrays and the identical numcodecs compressor the writer uses."""
    cfg = dict(cname="zstd", clevel=int(clevel), blocksize=BLOSC_BLOCK_BYTES)
    return (
        BloscCodec(shuffle="bitshuffle", typesize=4, **cfg),
        Blosc(shuffle=Blosc.BITSHUFFLE, typesize=4, **cfg),
    )


def error_bound_mm(encoding: str, max_abs_mm: float = 512.0) -> float:
    """Largest |decoded - input| in mm for coordinates with |x| <= max_abs_mm.

    "float32-qk": half the 2^-k mm quantum (the rounded value is exact in float32); "float32": one float32
    rounding, at most 2^-24 |x|.
    """
    scale = quantum_scale(encoding)
    return 0.5 / scale if scale else _F32_HALF_ULP_REL * max_abs_mm


def default_chunk_models(shard_models: int, levels=DEFAULT_LEVELS) -> int:
    """Models per inner chunk: the models along the last mode (len(levels)) when they tile the shard, else 1."""
    k = len(_levels_array(levels))
    return k if shard_models % k == 0 else 1


def vertex_selector(surface_vertex: np.ndarray) -> slice | np.ndarray:
    """``surface_vertex`` as a slice when it is a run of consecutive vertices (the template's: 28,322 ..
    81,093), else as an int64 array: a slice copies memory blocks, a fancy index gathers value by value
    (~5x slower on a 49-model batch)."""
    sv = np.asarray(surface_vertex, dtype=np.int64)
    if len(sv) and sv[-1] - sv[0] == len(sv) - 1 and np.all(np.diff(sv) == 1):
        return slice(int(sv[0]), int(sv[-1]) + 1)
    return sv


def hex_model_points(volume_points: np.ndarray, tri_points: np.ndarray, surface_vertex: np.ndarray) -> np.ndarray:
    """The hex model's nodes (..., n_volume + n_surface, 3) mm: its volume nodes (..., n_volume, 3), then
    the tri vertices ``surface_vertex`` (n_surface,) of tri_points (..., n_tri, 3)."""
    return np.concatenate([volume_points, tri_points[..., vertex_selector(surface_vertex), :]], axis=-2)


def create_store(
    path: str | Path,
    n_tri_nodes: int,
    n_hex_nodes: int,
    n_modes: int = DEFAULT_N_MODES,
    levels=DEFAULT_LEVELS,
    shard_models: int = DEFAULT_SHARD_MODELS,
    attrs: dict | None = None,
    encoding: str = "float32-q10",
    max_abs_mm: float = 512.0,
    chunk_models: int | None = None,
    clevel: int = BLOSC_CLEVEL,
    overwrite: bool = False,
    surface_vertex=None,
) -> zarr.Group:
    """Create the empty cohort store (Zarr v3) with ``weights``, ``tri/points``, ``hex/volume_points`` and
    ``hex/surface_vertex``.

    n_hex_nodes: nodes of the hex model; its last ``len(surface_vertex)`` nodes are the tri vertices
    ``surface_vertex`` (the template's ``surface_vertex``; None: none are shared, every node is stored).
    attrs: extra JSON attributes (e.g. ``ssm_sha256``, ``template_sha256`` from :func:`file_sha256`).
    max_abs_mm: the largest |coordinate| the store accepts (mm).  chunk_models: models per inner chunk
    (default :func:`default_chunk_models`); it must divide shard_models (a Zarr shard is whole chunks).
    clevel: blosc-zstd level of the point arrays.
    """
    for name, n in (("n_tri_nodes", n_tri_nodes), ("n_hex_nodes", n_hex_nodes)):
        if int(n) < 1:
            raise ValueError(f"{name} must be >= 1, got {n}")
    sv = np.zeros(0, np.int32) if surface_vertex is None else np.asarray(surface_vertex)
    if sv.ndim != 1 or not np.issubdtype(sv.dtype, np.integer):
        raise ValueError(f"surface_vertex must be a 1-D integer array of tri vertex ids, got {sv.dtype} {sv.shape}")
    if len(sv) and (sv.min() < 0 or sv.max() >= int(n_tri_nodes)):
        raise ValueError(
            f"surface_vertex must index the {n_tri_nodes} tri vertices, got range [{sv.min()}, {sv.max()}]"
        )
    n_volume = int(n_hex_nodes) - len(sv)
    if n_volume < 1:
        raise ValueError(f"the hex model's {n_hex_nodes} nodes leave no volume node after {len(sv)} surface nodes")
    scale = quantum_scale(encoding)  # 2^k, 0.0 unrounded; raises on an unknown encoding
    if not 0 < max_abs_mm < 2.0 ** (24 - QUANTUM_EXP):
        raise ValueError(f"max_abs_mm must be in (0, {2 ** (24 - QUANTUM_EXP)}) mm, got {max_abs_mm}")
    lv = _levels_array(levels)
    total = n_models(n_modes, lv)
    n_sh = n_shards(total, shard_models)
    cm = default_chunk_models(shard_models, lv) if chunk_models is None else int(chunk_models)
    if cm < 1 or shard_models % cm:
        raise ValueError(f"chunk_models={chunk_models} must be >= 1 and divide shard_models={shard_models}")
    blosc, _ = _blosc_codecs(clevel)
    if Path(path).exists() and not overwrite:
        raise ValueError(f"{path} already exists; pass overwrite=True to replace it")
    root = zarr.open_group(str(path), mode="w" if overwrite else "w-", zarr_format=3)
    root.attrs.update(
        {
            **(attrs or {}),
            "format": STORE_FORMAT,
            "units": "mm",
            "weights_units": "SD",
            "n_modes": int(n_modes),
            "levels": [float(v) for v in lv],
            "n_models": int(total),
            "model_id": "sum_i index(w_i in levels) * len(levels)^(n_modes - i), mode 1 most significant",
            "shard_models": int(shard_models),
            "chunk_models": cm,
            "n_shards": int(n_sh),
            "n_hex_nodes": int(n_hex_nodes),
            "hex_model": "node k of the hex model (k+1 of the template deck): hex/volume_points[i][k] for k < "
            "n_volume_nodes, else tri/points[i][hex/surface_vertex[k - n_volume_nodes]]",
            "encoding": encoding,
            "quantum_mm": 1.0 / scale if scale else None,
            "max_abs_mm": float(max_abs_mm),
            "error_bound_mm": error_bound_mm(encoding, max_abs_mm),
        }
    )
    root.create_array(
        "weights",
        shape=(total, n_modes),
        chunks=(shard_models, n_modes),
        dtype="f8",
        compressors=[ZstdCodec(level=3)],
        fill_value=np.nan,
        dimension_names=("model", "mode"),
    )
    for name, n in (("tri/points", n_tri_nodes), ("hex/volume_points", n_volume)):
        a = root.create_array(
            name,
            shape=(total, int(n), 3),
            chunks=(cm, int(n), 3),
            shards=(shard_models, int(n), 3),
            dtype="f4",
            filters=[TransposeCodec(order=CHUNK_ORDER)],
            compressors=[blosc],
            fill_value=0.0,
            dimension_names=("model", "node", "xyz"),
        )
        a.attrs.update({"units": "mm"})
    a = root.create_array(
        SURFACE_VERTEX,
        shape=(len(sv),),
        chunks=(max(len(sv), 1),),
        dtype="i4",
        compressors=[ZstdCodec(level=3)],
        fill_value=-1,
        dimension_names=("surface_node",),
    )
    if len(sv):
        a[:] = sv.astype(np.int32)
    a.attrs.update({"about": "tri vertex of each hex-model node after the volume nodes (0-based)"})
    root.create_group(
        _CHECKSUM_DIR,
        attributes={"about": "one subgroup per finished shard; attributes hold crc32c and size of its stored objects"},
    )
    return root


def create_store_for_run(
    path: str | Path,
    ssm: str | Path,
    hex_ssm: str | Path,
    template: str | Path,
    grid: dict,
    store: dict,
    attrs: dict | None = None,
    overwrite: bool = False,
) -> zarr.Group:
    """The run's empty store, as ``init_store`` makes it: node counts from the SSM's and the hex SSM's means,
    the shared skin from the template's ``surface_vertex``, the grid (``n_modes``, ``levels``) and the store
    settings (``shard_models``, ``encoding``, ``chunk_models``) of the config."""
    with np.load(ssm) as z:
        n_tri = z["mean"].shape[0]
    with np.load(hex_ssm) as z:
        n_hex = z["mean"].shape[0]
    with np.load(template) as z:  # the hex nodes that are tri vertices: stored once
        surface_vertex = z["surface_vertex"]
    return create_store(
        path,
        n_tri,
        n_hex,
        grid["n_modes"],
        grid["levels"],
        store["shard_models"],
        attrs=attrs,
        encoding=store["encoding"],
        chunk_models=store.get("chunk_models"),
        overwrite=overwrite,
        surface_vertex=surface_vertex,
    )


def _shard_objects(path: Path, shard: int) -> list[Path]:
    """Files holding shard ``shard``: the two point shards and the weights chunk (default key encoding)."""
    return [
        path / "tri/points/c" / str(shard) / "0" / "0",
        path / "hex/volume_points/c" / str(shard) / "0" / "0",
        path / "weights/c" / str(shard) / "0",
    ]


def _sidecar(shard: int) -> str:
    return f"{_CHECKSUM_DIR}/shard_{shard:05d}"


def _open_meta(path: str | Path) -> tuple[zarr.Group, dict]:
    p = Path(path)
    if not (p / "zarr.json").is_file():
        raise ValueError(f"{p} is not a cohort store (no zarr.json); create it with create_store")
    # the root zarr.json alone: opening the group would parse the arrays' metadata too, which fails on
    # codecs an older version used
    meta = json.loads((p / "zarr.json").read_text()).get("attributes", {})
    fmt = meta.get("format")
    if fmt != STORE_FORMAT:
        if isinstance(fmt, str) and fmt.startswith(_FORMAT_PREFIX):
            raise StoreVersionError(
                f"{p} was written by another spinecohort version (format {fmt!r}, this version reads "
                f"{STORE_FORMAT!r}); it cannot be read correctly. Rebuild it: "
                f"remove {p} and the shard records (results/shards/), then run snakemake again"
            )
        raise ValueError(f"{p} is not a spinecohort cohort store (format {fmt!r})")
    return zarr.open_group(str(p), mode="r"), meta


def read_model(path: str | Path, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(tri (n_tri_nodes, 3), hex (n_hex_nodes, 3): the whole hex model, :func:`hex_model_points`) float32
    node coordinates in mm of model ``i``."""
    root, meta = _open_meta(path)
    if not 0 <= int(i) < meta["n_models"]:
        raise ValueError(f"model {i} out of range [0, {meta['n_models']})")
    tri = root["tri/points"][int(i)]
    return tri, hex_model_points(root["hex/volume_points"][int(i)], tri, root[SURFACE_VERTEX][:])


#: what read_shard reads: a stored array, or "hex", the whole hex model assembled from both
SHARD_ARRAYS = (*POINT_ARRAYS, "hex")


def read_shard(path: str | Path, shard: int, array: str = "tri/points") -> np.ndarray:
    """Node coordinates (S, n_nodes, 3) float32 mm of all models of ``shard``: a stored point array, or
    ``"hex"``, the whole hex model (:func:`hex_model_points`)."""
    if array not in SHARD_ARRAYS:
        raise ValueError(f"array must be one of {SHARD_ARRAYS}, got {array!r}")
    root, meta = _open_meta(path)
    start, stop = shard_range(int(shard), meta["shard_models"], meta["n_models"])
    if array == "hex":
        return hex_model_points(
            root["hex/volume_points"][start:stop], root["tri/points"][start:stop], root[SURFACE_VERTEX][:]
        )
    return root[array][start:stop]
