"""The shard writer: one shard of both point arrays, streamed batch by batch into its Zarr shard objects.

:class:`ShardWriter` writes a shard object itself (the sharding format: the encoded inner chunks, then the
index of (offset, nbytes) uint64 pairs and its crc32c), streaming batch by batch, so a job never holds a
whole shard and computes each object's crc32c as it writes it.  Its bytes are identical to zarr-python's own write of the same array
(tested), and a second implementation (tensorstore) reads them (tested).  zarr-python and tensorstore
cannot stream a shard: they rewrite the whole shard object on each partial write, or hold the whole shard
in memory (docs/explanation/library-paths.md measures that path).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import google_crc32c
import numpy as np
import zarr

from spinecohort.store.chunks import _LINEAR_BLOCK, LinearPoints, _stored_chunks_nb
from spinecohort.store.format import (
    _EMPTY,
    FAULT_KILL_ENV,
    POINT_ARRAYS,
    SURFACE_VERTEX,
    _blosc_codecs,
    _open_meta,
    _shard_objects,
    _sidecar,
    quantize_mm,
    quantum_scale,
    vertex_selector,
)
from spinecohort.store.grid import model_name, shard_range, weights_of
from spinecohort.store.integrity import crc32c_hex


def _check_coordinates(name: str, shard: int, x: np.ndarray, max_abs_mm: float) -> None:
    lo, hi = float(x.min()), float(x.max())  # NaN propagates; no temporaries on large batches
    _check_range(name, shard, lo, hi, bool(np.isfinite(lo) and np.isfinite(hi)), max_abs_mm)


def _span(values: np.ndarray) -> tuple[float, float, bool]:
    """(min, max, all finite) of stored values, for the error message of :func:`_check_range`."""
    finite = np.isfinite(values)
    ok = values[finite]
    return float(ok.min(initial=np.inf)), float(ok.max(initial=-np.inf)), bool(finite.all())


def _check_range(name: str, shard: int, lo: float, hi: float, finite: bool, max_abs_mm: float) -> None:
    if not finite:
        raise ValueError(f"{name} of shard {shard} has non-finite coordinates")
    if max(-lo, hi) > max_abs_mm:
        raise ValueError(
            f"{name} of shard {shard} exceeds the store's max_abs_mm={max_abs_mm} "
            f"(coordinates span [{lo:.1f}, {hi:.1f}] mm)"
        )


def check_surface_nodes(tri: np.ndarray, hexp: np.ndarray, surface_vertex: np.ndarray, encoding: str, first_id: int):
    """Raise ValueError unless the last ``len(surface_vertex)`` nodes of the hex models hexp (B, n_hex, 3) mm
    round to the stored values of their tri vertices in tri (B, n_tri, 3) mm (the store keeps them once)."""
    sv = np.asarray(surface_vertex)
    n_vol = hexp.shape[1] - len(sv)
    sel = vertex_selector(sv)
    for k in range(len(hexp)):  # one model at a time: no shard-sized temporaries
        diff = (quantize_mm(hexp[k, n_vol:], encoding) != quantize_mm(tri[k, sel], encoding)).any(axis=1)
        if diff.any():
            node = n_vol + int(np.flatnonzero(diff)[0])
            raise ValueError(
                f"{model_name(first_id + k)}: hex node {node} is not its tri vertex {int(sv[node - n_vol])} as "
                f"stored ({int(diff.sum())} surface nodes differ); the store keeps each surface node once, in "
                "tri/points (hex/surface_vertex)"
            )


class ShardWriter:
    """Write shard ``shard`` of both point arrays batch by batch, then its weights and its sidecar.

    ``add(tri, hex)`` takes the next models of the shard in ID order (mm, any float dtype; batches a multiple
    of ``chunk_models`` except the last): tri (B, n_tri, 3) and hex either the volume nodes (B, n_volume, 3)
    or the whole hex model (B, n_hex_nodes, 3), whose surface nodes must then round to the stored values of
    their tri vertices (else ValueError: the store could not give them back).  It rounds them as stored,
    encodes each inner chunk (transpose, blosc)
    and appends it to ``<object>.<pid>.partial``; ``close()`` appends the shard index (offset and nbytes per
    chunk, uint64 little-endian, then its crc32c), moves the objects into place (rename: atomic), writes the
    weights and last the checksum sidecar, the shard's completion mark.  A writer that is not closed
    leaves no sidecar; the next writer of the shard removes the leftovers first.
    """

    def __init__(self, path: str | Path, shard: int):
        self.path = Path(path)
        root, meta = _open_meta(self.path)
        self.meta, self.shard = meta, int(shard)
        self.start, self.stop = shard_range(self.shard, meta["shard_models"], meta["n_models"])
        self.chunk = int(meta["chunk_models"])
        self.n_nodes = {name: root[name].shape[1] for name in POINT_ARRAYS}
        self.surface_vertex = np.asarray(root[SURFACE_VERTEX][:], dtype=np.int64)
        self.n_hex_nodes = int(meta["n_hex_nodes"])
        clevel = root["tri/points"].metadata.codecs[0].codecs[-1].clevel  # sharding -> inner chain -> blosc
        self._codec = _blosc_codecs(clevel)[1]
        self._clear()
        self.objects = dict(zip(POINT_ARRAYS, _shard_objects(self.path, self.shard)[:2]))
        self._tmp, self._files, self._index, self._crc, self._offset = {}, {}, {}, {}, {}
        for name, obj in self.objects.items():
            obj.parent.mkdir(parents=True, exist_ok=True)
            self._tmp[name] = obj.with_name(f"{obj.name}.{os.getpid()}.partial")
            self._files[name] = open(self._tmp[name], "wb")
            slots = meta["shard_models"] // self.chunk
            self._index[name] = np.full((slots, 2), _EMPTY, dtype="<u8")
            self._crc[name] = 0
            self._offset[name] = 0
        self._buffers = {}  # per array: float32 stored-order chunks of the largest batch so far
        self._scratch = (
            np.empty((self.chunk, _LINEAR_BLOCK), np.float32),
            np.empty(_LINEAR_BLOCK),
            np.empty(_LINEAR_BLOCK),
        )
        self.n_written = 0
        self.encode_cpu_s = 0.0  # CPU time in the codec alone (the benchmark's compression floor)
        self.stored_bytes = 0

    def _clear(self) -> None:
        """Remove the sidecar (a rewrite is incomplete until its new one lands), the shard's objects and
        any ``*.partial`` of a killed writer: zarr would otherwise read a stale index."""
        side = self.path / _sidecar(self.shard)
        if side.exists():
            for f in side.iterdir():
                f.unlink()
            side.rmdir()
        for obj in _shard_objects(self.path, self.shard):
            obj.unlink(missing_ok=True)
            if obj.parent.is_dir():
                for stale in obj.parent.glob(obj.name + ".*.partial"):
                    stale.unlink()

    def add(self, tri, hexp) -> None:
        """Append the next models: tri (B, n_tri, 3) mm, hex (B, n_volume, 3) or (B, n_hex_nodes, 3) mm; either
        may be a :class:`LinearPoints` (its chunks are formed in stored order as they are encoded)."""
        if not isinstance(tri, LinearPoints):
            tri = np.asarray(tri)
        if not isinstance(hexp, LinearPoints):
            hexp = np.asarray(hexp)
        n_vol = self.n_nodes["hex/volume_points"]
        if hexp.shape[1] == self.n_hex_nodes and self.n_hex_nodes != n_vol:
            if isinstance(tri, LinearPoints) or isinstance(hexp, LinearPoints):
                raise ValueError("the whole hex model is checked against float tri points: pass the volume nodes")
            self._check_surface(tri, hexp)
            hexp = hexp[:, :n_vol]
        batch = {"tri/points": tri, "hex/volume_points": hexp}
        b = len(tri)
        if len(hexp) != b:
            raise ValueError(f"tri and hex batches differ in models: {b} vs {len(hexp)}")
        if self.start + self.n_written + b > self.stop:
            raise ValueError(f"shard {self.shard} holds {self.stop - self.start} models; got {self.n_written + b}")
        if self.n_written % self.chunk:
            raise ValueError(f"only the last batch may be a partial chunk of {self.chunk} models")
        n_chunks = -(-b // self.chunk)  # a partial last chunk is the array's boundary chunk, zero-filled
        quantize = quantum_scale(self.meta["encoding"])  # 2^k, or 0.0: no rounding
        values = {}
        for name, x in batch.items():  # every chunk of the batch is formed and checked before any is encoded
            want = (self.n_nodes[name], 3)
            if len(x.shape) != 3 or x.shape[1:] != want:
                raise ValueError(f"{name} of shard {self.shard} must have shape (models, {want[0]}, 3), got {x.shape}")
            values[name] = self._buffer(name, n_chunks)
            if isinstance(x, LinearPoints):  # all chunks in one pass over the formula's terms
                if x.stored_chunks(quantize, self.meta["max_abs_mm"], values[name], self._scratch):
                    _check_range(name, self.shard, *_span(values[name]), self.meta["max_abs_mm"])
                continue
            if not np.issubdtype(x.dtype, np.floating):
                x = x.astype(np.float64)
            lo, hi, finite = _stored_chunks_nb(x, quantize, self.chunk, values[name])
            # checked on the stored float32 values (NaN and inf survive the rounding)
            _check_range(name, self.shard, lo, hi, finite, self.meta["max_abs_mm"])
        first_slot = self.n_written // self.chunk
        for name in batch:
            for j, c in enumerate(values[name]):  # c: one inner chunk, already in stored order
                self._append(name, first_slot + j, c)
        self.n_written += b

    def _buffer(self, name: str, n_chunks: int) -> np.ndarray:
        """(n_chunks, 3, nodes, chunk) float32 stored-order chunks of ``name``, reused batch after batch."""
        buf = self._buffers.get(name)
        if buf is None or len(buf) < n_chunks:
            buf = self._buffers[name] = np.empty((n_chunks, 3, self.n_nodes[name], self.chunk), np.float32)
        return buf[:n_chunks]

    def _append(self, name: str, slot: int, chunk: np.ndarray) -> None:
        """Encode one inner chunk (stored order) and append it to the array's shard object."""
        t0 = time.process_time()
        data = self._codec.encode(chunk)
        self.encode_cpu_s += time.process_time() - t0
        self._index[name][slot] = (self._offset[name], len(data))
        self._files[name].write(data)
        self._crc[name] = google_crc32c.extend(self._crc[name], data)
        self._offset[name] += len(data)

    def _check_surface(self, tri: np.ndarray, hexp: np.ndarray) -> None:
        if tri.ndim != 3 or len(tri) != len(hexp) or tri.shape[1] != self.n_nodes["tri/points"]:
            raise ValueError(
                f"tri/points of shard {self.shard} must have shape (models, {self.n_nodes['tri/points']}, 3)"
            )
        check_surface_nodes(tri, hexp, self.surface_vertex, self.meta["encoding"], self.start + self.n_written)

    def close(self) -> dict:
        """Finish the shard (index, rename, weights, sidecar); returns the sidecar record."""
        if self.start + self.n_written != self.stop:
            self.abort()
            raise ValueError(f"shard {self.shard} got {self.n_written} of its {self.stop - self.start} models")
        objects = {}
        for name, obj in self.objects.items():
            index = self._index[name].tobytes()
            tail = index + np.uint32(google_crc32c.value(index)).astype("<u4").tobytes()
            self._files[name].write(tail)
            self._crc[name] = google_crc32c.extend(self._crc[name], tail)
            self._files[name].close()
            os.replace(self._tmp[name], obj)
            objects[str(obj.relative_to(self.path))] = {
                "crc32c": crc32c_hex(self._crc[name]),
                "bytes": obj.stat().st_size,
            }
            self.stored_bytes += obj.stat().st_size
            if os.environ.get(FAULT_KILL_ENV) == str(self.shard):  # fault injection: die between the two arrays
                os.kill(os.getpid(), signal.SIGKILL)
        return self._finish(objects)

    def _finish(self, objects: dict) -> dict:
        """Write the shard's weights chunk, then its sidecar (the completion mark) recording ``objects`` (the
        point-array objects' crc32c and sizes) and the weights object's; returns the record."""
        rw = zarr.open_group(str(self.path), mode="r+")
        rw["weights"][self.start : self.stop] = weights_of(
            np.arange(self.start, self.stop), self.meta["n_modes"], self.meta["levels"]
        )
        w_obj = _shard_objects(self.path, self.shard)[2]
        objects[str(w_obj.relative_to(self.path))] = {
            "crc32c": crc32c_hex(google_crc32c.value(w_obj.read_bytes())),
            "bytes": w_obj.stat().st_size,
        }
        record = {"shard": self.shard, "models": [self.start, self.stop], "objects": objects}
        # zarr's LocalStore writes zarr.json through a temporary file and a rename: atomic on POSIX
        zarr.create_group(str(self.path), path=_sidecar(self.shard), attributes=record, zarr_format=3)
        return record

    def abort(self) -> None:
        """Drop what was written (the shard then reads as never written)."""
        for name, f in self._files.items():
            f.close()
            self._tmp[name].unlink(missing_ok=True)


def write_shard(path: str | Path, shard: int, tri_points: np.ndarray, hex_points: np.ndarray) -> dict:
    """Write shard ``shard`` whole: tri_points (S, n_tri_nodes, 3), hex_points (S, n_hex_nodes, 3) (the whole
    hex model) or (S, n_volume_nodes, 3) in mm, S = models in the shard.  Returns the sidecar record (see
    :class:`ShardWriter`)."""
    tri, hexp = np.asarray(tri_points), np.asarray(hex_points)
    root, meta = _open_meta(path)
    start, stop = shard_range(int(shard), meta["shard_models"], meta["n_models"])
    n_vol = root["hex/volume_points"].shape[1]
    for name, x, n in (
        ("tri/points", tri, (root["tri/points"].shape[1],)),
        ("hex points", hexp, tuple(sorted({meta["n_hex_nodes"], n_vol}))),
    ):
        if x.ndim != 3 or len(x) != stop - start or x.shape[1] not in n or x.shape[2] != 3:
            nodes = " or ".join(str(k) for k in n)
            raise ValueError(f"{name} of shard {shard} must have shape ({stop - start}, {nodes}, 3), got {x.shape}")
        _check_coordinates(name, shard, x, meta["max_abs_mm"])  # before the writer clears the old shard
    if hexp.shape[1] != n_vol:  # the whole hex model: its surface nodes must be the tri vertices
        sv = root[SURFACE_VERTEX][:]
        check_surface_nodes(tri, hexp, sv, meta["encoding"], start)
        hexp = hexp[:, :n_vol]
    writer = ShardWriter(path, shard)
    try:
        writer.add(tri, hexp)
    except BaseException:
        writer.abort()
        raise
    return writer.close()
