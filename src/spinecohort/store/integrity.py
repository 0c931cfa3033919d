"""The store's integrity: each finished shard's recorded crc32c and sizes against its objects, and the
removal of a shard so that the next run writes it again.

A shard job records, last, the crc32c (Castagnoli, the checksum of Zarr's ``crc32c`` codec) and size of
each of its objects in ``checksums/shard_NNNNN``; a shard without that record was never finished.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import google_crc32c

from spinecohort.store.format import _open_meta, _shard_objects, _sidecar


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file (for the SSM/template checksums recorded in the store attributes)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def crc32c_hex(crc: int) -> str:
    """A crc32c value as the shard records write it: 8 lowercase hex digits."""
    return f"{crc & 0xFFFFFFFF:08x}"


def object_crc32c(path: str | Path) -> str:
    """crc32c (Castagnoli, the checksum of Zarr's ``crc32c`` codec and of the shard index) of a shard object,
    as :func:`crc32c_hex`.

    The shard records hold crc32c, not sha256 (docs/explanation/performance.md): they detect corruption and
    interrupted writes, which a 32-bit CRC does (every burst up to 32 bits, any other change but for
    2^-32), several times faster than sha256; tampering is the release's concern, whose BagIt manifests
    hold sha256."""
    crc = 0
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(8 << 20), b""):
            crc = google_crc32c.extend(crc, block)
    return crc32c_hex(crc)


def shard_problems(path: str | Path) -> dict[int, str]:
    """Shards that must be (re)written, with why: no sidecar (never finished, or killed), a missing
    object, or an object whose size or crc32c differs from the one recorded when it was written."""
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
            elif object_crc32c(obj) != want["crc32c"]:
                bad[s] = f"{rel} is corrupt (crc32c differs from the one recorded at write time)"
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
