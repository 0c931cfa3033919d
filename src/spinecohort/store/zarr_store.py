"""The sharded Zarr v3 store of the virtual cohort (``results/cohort.zarr``).

Layout (one store, written shard by shard by independent jobs)::

    weights      (n_models, n_modes)       float64, SD units; one chunk per shard
    tri/points   (n_models, n_tri_nodes, 3) float32 mm on read; one model per chunk, shard_models per shard
    hex/points   (n_models, n_hex_nodes, 3) float32 mm on read; same chunking
    checksums/shard_NNNNN                  per-shard group whose attributes hold the sha256 of the shard's
                                           stored objects; written last, atomically: the completion mark

Model IDs are mixed-radix numbers of the SD-level indices, mode 1 most significant
(``model_id = sum_i (w_i + 3) * 7^(5 - i)`` on the default 5 x {-3..3} grid); a shard is the contiguous
ID range ``[shard * shard_models, (shard + 1) * shard_models)``, so with 343 models per shard the five
modes split into 49 shards of fixed (w_1, w_2).

Encoding (chosen by measurement, see docs/store.md): coordinates are quantized to a fixed quantum
(0.001 mm) by numcodecs' FixedScaleOffset, transposed so each chunk is three runs of x, y, z along the
node order, delta-coded along the nodes (neighbouring mesh nodes are close, so deltas are small), then
byte-shuffled and zstd-compressed.  A plain ``zarr.open(path)["hex/points"][i]`` decodes to millimetres
(float32) without project code: 3.7 bytes per stored node at 81k nodes per model, 4.9 at 17k, against
about 11 for float32+zstd.  All codecs come from zarr/numcodecs; only the layout is ours.

Why writes go through :func:`write_shard`: the numcodecs filters flatten their input with
``reshape(-1, order="A")``; after the transpose codec a C-ordered chunk is an F-contiguous view, which
would delta-code the interleaved xyz order and decode wrongly.  Writing with the array's memory order
set to "F" makes the transposed view C-contiguous, so the stored bytes are exactly what the codec chain
specifies (reading needs no special config).  :func:`write_shard` verifies every shard it writes by
decoding it again, so a change of that behaviour in zarr/numcodecs fails loudly instead of silently.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import signal
import warnings
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import Delta, FixedScaleOffset, Shuffle, TransposeCodec, ZstdCodec

#: SD levels of the default grid and number of modes (5 x {-3..3} -> 16,807 models).
DEFAULT_LEVELS = (-3, -2, -1, 0, 1, 2, 3)
DEFAULT_N_MODES = 5
DEFAULT_SHARD_MODELS = 343
#: Coordinate quantum of the integer encodings, mm (far below the 0.04 mm morph tolerance).
DEFAULT_QUANTUM_MM = 0.001
ENCODINGS = ("int32-delta", "int32", "float32")
POINT_ARRAYS = ("tri/points", "hex/points")
STORE_FORMAT = "spinecohort.cohort-store/1"
_CHECKSUM_DIR = "checksums"
#: fault injection for the kill-and-resume test: a process with this variable set to a shard number is
#: SIGKILLed by ``write_shard`` after that shard's first array is written (as a node failure would)
FAULT_KILL_ENV = "SPINECOHORT_FAULT_KILL_SHARD"
# float32 spacing relative to magnitude; three roundings (input cast, scaled product, decoded cast)
# each contribute at most half an ulp.
_F32_HALF_ULP_REL = 2.0**-24


def _quiet_numcodecs(func):
    """Silence zarr's 'numcodecs codecs are not in the v3 spec' warning, raised on every metadata parse."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Numcodecs codecs are not in the Zarr", category=UserWarning)
            return func(*args, **kwargs)

    return wrapper


# --------------------------------------------------------------------------------------------- IDs
def _levels_array(levels) -> np.ndarray:
    lv = np.asarray(levels, dtype=np.float64)
    if lv.ndim != 1 or lv.size < 1:
        raise ValueError(f"levels must be a non-empty 1-D sequence of SD values, got {levels!r}")
    if np.any(np.diff(lv) <= 0):
        raise ValueError(f"levels must be strictly increasing, got {list(lv)}")
    return lv


def n_models(n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> int:
    """Number of models on the grid: len(levels) ** n_modes (7^5 = 16,807 by default)."""
    if n_modes < 1:
        raise ValueError(f"n_modes must be >= 1, got {n_modes}")
    return len(_levels_array(levels)) ** int(n_modes)


def model_id(weights, levels=DEFAULT_LEVELS) -> np.ndarray:
    """Model IDs of grid weights (..., n_modes) in SD units; mode 1 is the most significant digit.

    On the default grid this is ``sum_i (w_i + 3) * 7^(n_modes - i)``.  Weights must lie on the grid.
    """
    lv = _levels_array(levels)
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim < 1:
        raise ValueError("weights must have a trailing mode axis")
    digit = np.searchsorted(lv, w)
    digit_c = np.clip(digit, 0, lv.size - 1)
    if np.any(np.abs(lv[digit_c] - w) > 1e-9) or np.any(digit >= lv.size):
        raise ValueError(f"weights off the grid levels {list(lv)}")
    place = lv.size ** np.arange(w.shape[-1] - 1, -1, -1, dtype=np.int64)
    return digit_c.astype(np.int64) @ place


def weights_of(ids, n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> np.ndarray:
    """Grid weights (..., n_modes) in SD units of model IDs (...); inverse of :func:`model_id`."""
    lv = _levels_array(levels)
    i = np.asarray(ids)
    if not np.issubdtype(i.dtype, np.integer):
        raise ValueError(f"model IDs must be integers, got dtype {i.dtype}")
    total = lv.size ** int(n_modes)
    if np.any(i < 0) or np.any(i >= total):
        raise ValueError(f"model IDs must lie in [0, {total}), got range [{i.min()}, {i.max()}]")
    place = lv.size ** np.arange(n_modes - 1, -1, -1, dtype=np.int64)
    digits = (i.astype(np.int64)[..., None] // place) % lv.size
    return lv[digits]


def grid_weights(n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> np.ndarray:
    """All grid weights (n_models, n_modes) in SD units, row k = weights of model k."""
    return weights_of(np.arange(n_models(n_modes, levels)), n_modes, levels)


def model_name(ids) -> list[str] | str:
    """``model_00000``-style names of one ID or an array of IDs."""
    if np.ndim(ids) == 0:
        return f"model_{int(ids):05d}"
    return [f"model_{int(k):05d}" for k in np.ravel(ids)]


def n_shards(total_models: int, shard_models: int = DEFAULT_SHARD_MODELS) -> int:
    """Number of shards covering total_models IDs (the last one may be partial)."""
    if shard_models < 1:
        raise ValueError(f"shard_models must be >= 1, got {shard_models}")
    return -(-int(total_models) // int(shard_models))


def shard_range(
    shard: int, shard_models: int = DEFAULT_SHARD_MODELS, total_models: int | None = None
) -> tuple[int, int]:
    """Half-open model-ID range [start, stop) of ``shard``; clipped to total_models when given."""
    if shard_models < 1:
        raise ValueError(f"shard_models must be >= 1, got {shard_models}")
    if shard < 0 or (total_models is not None and shard >= n_shards(total_models, shard_models)):
        raise ValueError(f"shard {shard} out of range for {total_models} models in shards of {shard_models}")
    start = int(shard) * int(shard_models)
    stop = start + int(shard_models)
    return start, stop if total_models is None else min(stop, int(total_models))


# ---------------------------------------------------------------------------------------- encoding
def _codecs(encoding: str, quantum_mm: float) -> dict:
    """filters/compressors for create_array and the write-time memory order the chain needs."""
    if encoding == "float32":
        return dict(filters=None, compressors=[ZstdCodec(level=3)], order="C")
    if not (0 < quantum_mm <= DEFAULT_QUANTUM_MM):
        raise ValueError(f"quantum_mm must be in (0, {DEFAULT_QUANTUM_MM}] mm, got {quantum_mm}")
    scale = 1.0 / quantum_mm
    # numcodecs stores the scale as given; an integral scale keeps the JSON readable and the codec exact
    scale = int(round(scale)) if abs(scale - round(scale)) < 1e-9 else scale
    fso = FixedScaleOffset(offset=0, scale=scale, dtype="<f4", astype="<i4")
    # byte shuffle + zstd 3: as small as Blosc-zstd 5 (3.6 vs 3.57 B/node at 81k nodes) at a third of the
    # encode time; bitshuffle and higher levels measured larger or much slower (docs/store.md)
    packed = [Shuffle(elementsize=4), ZstdCodec(level=3)]
    if encoding == "int32":
        return dict(filters=[fso], compressors=packed, order="C")
    if encoding == "int32-delta":
        return dict(filters=[TransposeCodec(order=(0, 2, 1)), fso, Delta(dtype="<i4")], compressors=packed, order="F")
    raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")


def error_bound_mm(encoding: str, quantum_mm: float = DEFAULT_QUANTUM_MM, max_abs_mm: float = 512.0) -> float:
    """Largest |decoded - input| in mm for coordinates with |x| <= max_abs_mm.

    Integer encodings: half a quantum plus three float32 roundings (input cast, scaled product, decoded
    value), each at most 2^-24 |x|; float32: one rounding.
    """
    if encoding == "float32":
        return _F32_HALF_ULP_REL * max_abs_mm
    if encoding in ("int32", "int32-delta"):
        return 0.5 * quantum_mm + 3 * _F32_HALF_ULP_REL * max_abs_mm
    raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")


# ------------------------------------------------------------------------------------------- create
@_quiet_numcodecs
def create_store(
    path: str | Path,
    n_tri_nodes: int,
    n_hex_nodes: int,
    n_modes: int = DEFAULT_N_MODES,
    levels=DEFAULT_LEVELS,
    shard_models: int = DEFAULT_SHARD_MODELS,
    attrs: dict | None = None,
    encoding: str = "int32-delta",
    quantum_mm: float = DEFAULT_QUANTUM_MM,
    max_abs_mm: float = 512.0,
    overwrite: bool = False,
) -> zarr.Group:
    """Create the empty cohort store (Zarr v3) with ``weights``, ``tri/points`` and ``hex/points``.

    attrs: extra JSON attributes (e.g. ``ssm_sha256``, ``template_sha256`` from :func:`file_sha256`).
    max_abs_mm: the largest |coordinate| the store accepts; it sets the stated error bound and keeps the
    integer deltas inside int32.
    """
    for name, n in (("n_tri_nodes", n_tri_nodes), ("n_hex_nodes", n_hex_nodes)):
        if int(n) < 1:
            raise ValueError(f"{name} must be >= 1, got {n}")
    lv = _levels_array(levels)
    total = n_models(n_modes, lv)
    n_sh = n_shards(total, shard_models)
    enc = _codecs(encoding, quantum_mm)  # validates before anything is created
    if encoding != "float32" and 2 * max_abs_mm / quantum_mm >= 2**31:
        raise ValueError(f"max_abs_mm={max_abs_mm} overflows int32 deltas at quantum {quantum_mm} mm")
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
            "n_shards": int(n_sh),
            "encoding": encoding,
            "quantum_mm": float(quantum_mm) if encoding != "float32" else None,
            "max_abs_mm": float(max_abs_mm),
            "error_bound_mm": error_bound_mm(encoding, quantum_mm, max_abs_mm),
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
    for name, n in (("tri/points", n_tri_nodes), ("hex/points", n_hex_nodes)):
        a = root.create_array(
            name,
            shape=(total, int(n), 3),
            chunks=(1, int(n), 3),
            shards=(shard_models, int(n), 3),
            dtype="f4",
            filters=enc["filters"],
            compressors=enc["compressors"],
            fill_value=0.0,
            dimension_names=("model", "node", "xyz"),
        )
        a.attrs.update({"units": "mm"})
    root.create_group(
        _CHECKSUM_DIR,
        attributes={"about": "one subgroup per finished shard; attributes hold sha256 and size of its stored objects"},
    )
    return root


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file (for the SSM/template checksums recorded in the store attributes)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# -------------------------------------------------------------------------------------------- write
def _shard_objects(path: Path, shard: int) -> list[Path]:
    """Files holding shard ``shard``: the two point shards and the weights chunk (default key encoding)."""
    return [
        path / "tri/points/c" / str(shard) / "0" / "0",
        path / "hex/points/c" / str(shard) / "0" / "0",
        path / "weights/c" / str(shard) / "0",
    ]


def _sidecar(shard: int) -> str:
    return f"{_CHECKSUM_DIR}/shard_{shard:05d}"


def _open_meta(path: str | Path) -> tuple[zarr.Group, dict]:
    p = Path(path)
    if not (p / "zarr.json").is_file():
        raise ValueError(f"{p} is not a cohort store (no zarr.json); create it with create_store")
    root = zarr.open_group(str(p), mode="r")
    meta = dict(root.attrs)
    if meta.get("format") != STORE_FORMAT:
        raise ValueError(f"{p} is not a spinecohort cohort store (format {meta.get('format')!r})")
    return root, meta


@_quiet_numcodecs
def write_shard(
    path: str | Path, shard: int, tri_points: np.ndarray, hex_points: np.ndarray, verify: bool = True
) -> dict:
    """Write shard ``shard`` (its exact shard-aligned region of both point arrays and ``weights``).

    tri_points (S, n_tri_nodes, 3), hex_points (S, n_hex_nodes, 3) in mm, S = models in the shard.
    After the data, a checksum sidecar is written atomically; it is the shard's completion mark.
    Returns the sidecar record.
    """
    p = Path(path)
    root, meta = _open_meta(p)
    total, sm = meta["n_models"], meta["shard_models"]
    start, stop = shard_range(int(shard), sm, total)
    arrays = {"tri/points": np.asarray(tri_points), "hex/points": np.asarray(hex_points)}
    for name, x in arrays.items():
        want = (stop - start, root[name].shape[1], 3)
        if x.shape != want:
            raise ValueError(f"{name} of shard {shard} must have shape {want}, got {x.shape}")
        lo, hi = float(x.min()), float(x.max())  # NaN propagates; no temporaries on ~1 GB shards
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise ValueError(f"{name} of shard {shard} has non-finite coordinates")
        if max(-lo, hi) > meta["max_abs_mm"]:
            raise ValueError(
                f"{name} of shard {shard} exceeds the store's max_abs_mm={meta['max_abs_mm']} "
                f"(coordinates span [{lo:.1f}, {hi:.1f}] mm)"
            )
    side = p / _sidecar(shard)
    if side.exists():  # a rewrite is incomplete until its new sidecar lands
        for f in side.iterdir():
            f.unlink()
        side.rmdir()
    # Start from nothing: zarr reads an existing shard's index even on a full-shard write, so a corrupt
    # object would fail the rewrite; a job killed inside zarr's atomic write leaves a *.partial file,
    # which would make the store differ from an uninterrupted run.
    for obj in _shard_objects(p, shard):
        obj.unlink(missing_ok=True)
        if obj.parent.is_dir():
            for stale in obj.parent.glob(obj.name + ".*.partial"):
                stale.unlink()
    order = "F" if meta["encoding"] == "int32-delta" else "C"
    rw = zarr.open_group(str(p), mode="r+")
    levels = meta["levels"]
    rw["weights"][start:stop] = weights_of(np.arange(start, stop), meta["n_modes"], levels)
    max_err = {}
    for name, x in arrays.items():
        arr = rw[name].with_config({"order": order})
        arr[start:stop] = x
        if os.environ.get(FAULT_KILL_ENV) == str(shard):  # fault injection: die between the two arrays
            os.kill(os.getpid(), signal.SIGKILL)
        if verify:
            # float32 difference: half the memory traffic; its own rounding (<= 2^-24 |x|) is covered by
            # the bound's float32 terms
            diff = np.subtract(root[name][start:stop], x, dtype=np.float32)
            max_err[name] = float(max(diff.max(), -diff.min()))
            if max_err[name] > meta["error_bound_mm"]:
                raise RuntimeError(
                    f"{name} shard {shard} decodes with error {max_err[name]:.3g} mm > bound "
                    f"{meta['error_bound_mm']:.3g} mm: the codec chain misbehaves"
                )
    record = {
        "shard": int(shard),
        "models": [start, stop],
        "objects": {
            str(o.relative_to(p)): {"sha256": file_sha256(o), "bytes": o.stat().st_size}
            for o in _shard_objects(p, shard)
        },
        "max_error_mm": max_err,
    }
    # zarr's LocalStore writes zarr.json through a temporary file and a rename: atomic on POSIX
    zarr.create_group(str(p), path=_sidecar(shard), attributes=record, zarr_format=3)
    return record


# --------------------------------------------------------------------------------------------- read
@_quiet_numcodecs
def read_model(path: str | Path, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(tri (n_tri_nodes, 3), hex (n_hex_nodes, 3)) float32 node coordinates in mm of model ``i``."""
    root, meta = _open_meta(path)
    if not 0 <= int(i) < meta["n_models"]:
        raise ValueError(f"model {i} out of range [0, {meta['n_models']})")
    return root["tri/points"][int(i)], root["hex/points"][int(i)]


@_quiet_numcodecs
def read_shard(path: str | Path, shard: int, array: str = "tri/points") -> np.ndarray:
    """Node coordinates (S, n_nodes, 3) float32 mm of all models of ``shard`` from ``array``."""
    if array not in POINT_ARRAYS:
        raise ValueError(f"array must be one of {POINT_ARRAYS}, got {array!r}")
    root, meta = _open_meta(path)
    start, stop = shard_range(int(shard), meta["shard_models"], meta["n_models"])
    return root[array][start:stop]


@_quiet_numcodecs
def shard_problems(path: str | Path) -> dict[int, str]:
    """Shards that must be (re)written, with why: no sidecar (never finished, or killed), a missing
    object, or an object whose size or sha256 differs from the one recorded when it was written."""
    p = Path(path)
    _, meta = _open_meta(p)
    bad = {}
    for s in range(meta["n_shards"]):
        side = p / _sidecar(s) / "zarr.json"
        if not side.is_file():
            bad[s] = "no checksum record (never written, or its job was killed before it finished)"
            continue
        rec = json.loads(side.read_text())["attributes"]
        for rel, want in rec["objects"].items():
            obj = p / rel
            if not obj.is_file():
                bad[s] = f"{rel} is missing"
            elif obj.stat().st_size != want["bytes"]:
                bad[s] = f"{rel} has {obj.stat().st_size} bytes, {want['bytes']} were written"
            elif file_sha256(obj) != want["sha256"]:
                bad[s] = f"{rel} is corrupt (sha256 differs from the one recorded at write time)"
            if s in bad:
                break
    return bad


def check_store(path: str | Path) -> list[int]:
    """Shards that must be (re)written (``shard_problems`` without the reasons)."""
    return sorted(shard_problems(path))


def invalidate_shard(path: str | Path, shard: int) -> list[Path]:
    """Remove shard ``shard``'s checksum record and data objects, so that it reads as never written and
    its next ``write_shard`` starts from nothing.  Returns the files removed."""
    p = Path(path)
    _open_meta(p)
    removed = []
    side = p / _sidecar(shard)
    if side.is_dir():
        for f in side.iterdir():
            f.unlink()
            removed.append(f)
        side.rmdir()
    for obj in _shard_objects(p, shard):
        if obj.is_file():
            obj.unlink()
            removed.append(obj)
    return removed
