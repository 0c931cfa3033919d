"""The store as one uncompressed zip (a Zarr v3 zip store), and reproducible, safely extracted zips.

Zarr readers open ``cohort.zarr.zip`` in place, from disk or over HTTP range requests: members are stored,
not deflated, so a shard's index and each inner chunk are byte ranges of the zip (the chunks are already
blosc-compressed; deflate would gain little and hide them behind a second codec).  A zip is reproducible:
members sorted, date 1980-01-01, mode 0644, no directory entries, ZIP64 only where a size or offset needs it.
Extraction accepts only names that stay inside the destination (no absolute name, no ``..``) and no
symlink entries, checked for every member before anything is written.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import struct
import zipfile
from pathlib import Path

import google_crc32c

from spinecohort.release.names import ZIP_DATE_TIME, ReleaseError, safe_relpath

_BLOCK = 8 << 20  # bytes per read while copying or checksumming a member


def store_files(store: str | Path) -> list[str]:
    """Relative POSIX paths of every file of the store, sorted; hidden files (Snakemake's ``.initialized``
    marker) are not part of the data.  A leftover ``*.partial`` write or a symlink is refused."""
    root = Path(store)
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for f in filenames:
            if f.startswith("."):
                continue
            p = Path(dirpath) / f
            rel = p.relative_to(root).as_posix()
            if p.is_symlink() or not p.is_file():
                raise ReleaseError(f"{p}: the store may hold only regular files (found a link or special file)")
            if f.endswith(".partial"):
                raise ReleaseError(f"{p}: unfinished zarr write in the store; rerun its shard first")
            out.append(safe_relpath(rel, f"store file {p}"))
    return sorted(out)


def _entry(name: str, size: int, compress: int) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=ZIP_DATE_TIME)
    info.compress_type = compress
    info.external_attr = (stat.S_IFREG | 0o644) << 16
    info.create_system = 3  # unix: the mode above is read as such
    info.file_size = size  # known up front: ZIP64 headers only for members that need them
    # deflate level 1 (the entry's own level: ZipFile.open ignores the archive's): on the test bag ~15 % larger
    # than level 6, 4x faster
    info._compresslevel = 1  # ZipInfo.compress_level from Python 3.13, which keeps this name as its alias
    return info


def write_zip(path: str | Path, root: str | Path, members, *, compress: int = zipfile.ZIP_STORED) -> Path:
    """Zip ``root/member`` files as ``member`` (sorted order given), reproducibly: same files -> same bytes."""
    root, path = Path(root), Path(path)
    with zipfile.ZipFile(path, "w", compression=compress, allowZip64=True) as zf:
        for rel in members:
            src = root / safe_relpath(rel, f"zip member of {path}")
            size = src.stat().st_size
            with open(src, "rb") as fin, zf.open(_entry(rel, size, compress), "w") as fout:
                shutil.copyfileobj(fin, fout, _BLOCK)
    return path


def write_store_zip(path: str | Path, store: str | Path) -> dict:
    """The store as one uncompressed zip at ``path``; returns its member count and bytes."""
    members = store_files(store)
    write_zip(path, store, members)
    return {"members": len(members), "bytes": Path(path).stat().st_size}


def zip_references(path: str | Path) -> dict:
    """Where each member's bytes lie in an uncompressed zip, as fsspec references (spec version 1):
    ``{"version": 1, "zip_bytes": size, "refs": {member: [null, offset, nbytes]}}``, the zarr metadata
    documents (``zarr.json``) inlined as text.  A null URL means "the target", the zip's own URL, which
    the reader supplies: the references do not depend on where the zip is published.  An HTTP reader then
    fetches a shard's index and a chunk as exact byte ranges (a generic zip reader seeks from a member's
    start, and tensorstore's zip driver reads whole members: the shard objects are GBs)."""
    path = Path(path)
    refs = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        for info in sorted(zf.infolist(), key=lambda i: i.filename):
            if info.compress_type != zipfile.ZIP_STORED:
                raise ReleaseError(f"{path.name}: member {info.filename} is compressed; a store zip must be stored")
            if info.filename.rsplit("/", 1)[-1] == "zarr.json":
                refs[info.filename] = zf.read(info).decode("utf-8")
                continue
            f.seek(info.header_offset)
            head = f.read(30)  # local file header: the name and extra field lengths end it
            if len(head) != 30 or head[:4] != b"PK\x03\x04":
                raise ReleaseError(f"{path.name}: no local header for {info.filename} at {info.header_offset}")
            n_name, n_extra = struct.unpack("<HH", head[26:30])
            refs[info.filename] = [None, info.header_offset + 30 + n_name + n_extra, info.file_size]
    return {"version": 1, "zip_bytes": path.stat().st_size, "refs": refs}


def write_references(path: str | Path, zip_path: str | Path) -> dict:
    """Write :func:`zip_references` of ``zip_path`` to ``path`` (sorted keys: reproducible)."""
    refs = zip_references(zip_path)
    Path(path).write_text(json.dumps(refs, sort_keys=True, separators=(",", ":")) + "\n", encoding="utf-8")
    return refs


def _member_crc32c(zf: zipfile.ZipFile, name: str) -> tuple[str, int]:
    """(crc32c hex, bytes) of a member, read in blocks (zipfile checks the zip's own CRC-32 on the way)."""
    from spinecohort.store.zarr_store import crc32c_hex

    crc, n = 0, 0
    with zf.open(name) as f:
        while block := f.read(_BLOCK):
            crc = google_crc32c.extend(crc, block)
            n += len(block)
    return crc32c_hex(crc), n


def store_zip_problems(path: str | Path) -> list[str]:
    """What is wrong with a store zip, checked in place (nothing unpacked): not a zip, not a cohort store,
    a shard without its checksum record, a shard object missing, of another size or crc32c than recorded
    when it was written, or any member failing the zip's own CRC-32.  Empty list: every shard is intact."""
    path = Path(path)
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        return [f"{path.name}: not a readable zip ({exc}); truncated or not a store zip"]
    problems = []
    with zf:
        names = set(zf.namelist())
        bad_names = [n for n in names if _unsafe(n)]
        if bad_names:
            return [f"{path.name}: member {n!r} is not a safe relative name" for n in sorted(bad_names)]
        if "zarr.json" not in names:
            return [f"{path.name}: no zarr.json at its root; not a cohort store zip"]
        attrs = json.loads(zf.read("zarr.json")).get("attributes", {})
        checked = set()
        for s in range(int(attrs.get("n_shards", 0))):
            side = f"checksums/shard_{s:05d}/zarr.json"
            if side not in names:
                problems.append(f"{path.name}: shard {s} has no checksum record ({side}); never finished")
                continue
            checked.add(side)
            for rel, want in json.loads(zf.read(side))["attributes"]["objects"].items():
                if rel not in names:
                    problems.append(f"{path.name}: {rel} (shard {s}) is missing")
                    continue
                try:
                    crc, n = _member_crc32c(zf, rel)
                except zipfile.BadZipFile as exc:
                    problems.append(f"{path.name}: {rel} (shard {s}) is corrupt ({exc})")
                    continue
                checked.add(rel)
                if n != want["bytes"]:
                    problems.append(f"{path.name}: {rel} has {n} bytes, {want['bytes']} were written")
                elif crc != want["crc32c"]:
                    problems.append(
                        f"{path.name}: {rel} is corrupt (crc32c differs from the one recorded at write time)"
                    )
        for rel in sorted(names - checked):  # metadata: the zip's CRC-32 alone
            try:
                zf.read(rel)
            except zipfile.BadZipFile as exc:
                problems.append(f"{path.name}: {rel} is corrupt ({exc})")
    return problems


def _unsafe(name: str) -> bool:
    try:
        safe_relpath(name.rstrip("/"), "member")
    except ReleaseError:
        return True
    return False


def safe_extract(archive: str | Path, dest: str | Path) -> list[str]:
    """Unpack a zip into ``dest``; returns the member names (files only).

    Every member is checked before anything is written: relative names without ``..`` that resolve inside
    ``dest``, no symlink entries.  A truncated or corrupt zip (or a member failing its CRC-32) raises
    ReleaseError naming it."""
    archive, dest = Path(archive), Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    try:
        with zipfile.ZipFile(archive) as zf:
            infos = zf.infolist()
            for m in infos:
                if stat.S_ISLNK(m.external_attr >> 16):
                    raise ReleaseError(f"{archive}: member {m.filename!r} is a symlink; only regular files are allowed")
                target = (dest / m.filename).resolve()
                if _unsafe(m.filename) or not target.is_relative_to(dest.resolve()):
                    raise ReleaseError(
                        f"{archive}: member {m.filename!r} would be written outside the extraction directory "
                        "(absolute name or '..')"
                    )
            files = [m for m in infos if not m.is_dir()]
            for m in files:
                out = dest / m.filename
                out.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(m) as fin, open(out, "wb") as fout:
                    shutil.copyfileobj(fin, fout, _BLOCK)
    except (zipfile.BadZipFile, EOFError) as exc:
        raise ReleaseError(f"{archive}: not a complete zip archive ({exc})") from None
    return [m.filename for m in files]
