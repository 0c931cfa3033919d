"""Verifying a release bag (BagIt checks, then the store zip checked and read in place) and finding what
``spinecohort export`` needs inside a release."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from spinecohort.release.archive import store_zip_problems, zip_references
from spinecohort.release.names import (
    FILES_RECORD,
    MODEL_INPUTS,
    RELEASE_JSON,
    STORE_REFS,
    STORE_ZIP,
    ReleaseError,
    safe_relpath,
)


def _tag_problems(bag, root: Path) -> list[str]:
    """Files outside data/ that no tag manifest lists (bagit only checks the payload for extras)."""
    listed = set(bag.tagfile_entries())
    fixed = {
        "bagit.txt",
        *(Path(f).name for f in bag.manifest_files()),
        *(Path(f).name for f in bag.tagmanifest_files()),
    }
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and not rel.startswith("data/") and rel not in listed and rel not in fixed:
            out.append(f"{rel}: in the bag but not in tagmanifest-sha256.txt (extra file)")
    return out


def verify_release(bag_dir: str | Path, processes: int = 1, store: bool = True) -> dict:
    """Check a release bag; raise ReleaseError listing every problem found.

    1. BagIt: no file missing, no extra file (payload and tag files), every size as recorded in
       metadata/files.json, every sha256 in the manifests (``bagit.Bag.validate``).
    2. store=True: ``data/cohort.zarr.zip`` checked in place (nothing unpacked): every shard object's size
       and crc32c as recorded when its shard was written, every member's zip CRC-32; then its first and
       last model read through zarr's zip store, finite, and its model count equal to files.json's; and
       ``data/cohort.zarr.refs.json`` gives exactly its members' byte ranges.
    Returns counts and the time taken.
    """
    import bagit

    t0 = time.perf_counter()
    root = Path(bag_dir)
    if not root.is_dir():
        raise ReleaseError(f"{root}: no such release directory")
    try:
        bag = bagit.Bag(str(root))
    except bagit.BagError as exc:
        raise ReleaseError(f"{root}: not a BagIt bag ({exc})") from None
    missing, extra = bag.compare_manifests_with_fs()
    problems = [f"{p}: listed in the manifest but missing" for p in sorted(missing)]
    problems += [f"{p}: in the bag but not in manifest-sha256.txt (extra file)" for p in sorted(extra)]
    problems += _tag_problems(bag, root)
    files_path = root / FILES_RECORD
    record = {}
    if files_path.is_file():
        try:
            record = json.loads(files_path.read_text())
        except json.JSONDecodeError as exc:
            problems.append(f"{FILES_RECORD}: not valid JSON ({exc})")
    for f in record.get("files", []):
        p = root / safe_relpath(f["key"], f"{FILES_RECORD} file key")
        if p.is_file() and p.stat().st_size != f["size"]:
            problems.append(
                f"{f['key']}: {p.stat().st_size} bytes, but {FILES_RECORD} records {f['size']} (truncated or replaced)"
            )
    if not problems:
        try:
            bag.validate(processes=processes)
        except bagit.BagValidationError as exc:
            details = getattr(exc, "details", None) or []
            problems += [_describe_bagit(d) for d in details] or [str(exc)]
    if problems:
        raise ReleaseError(f"{root}: release does not verify:\n  " + "\n  ".join(problems))
    n_payload = len(bag.payload_entries())
    report = {"files": n_payload, "bytes": sum((root / k).stat().st_size for k in bag.payload_entries())}
    if store:
        report.update(check_store_zip(root / "data" / STORE_ZIP, record.get("counts", {}).get("n_models")))
        refs = root / "data" / STORE_REFS
        if not refs.is_file() or json.loads(refs.read_text()) != zip_references(root / "data" / STORE_ZIP):
            raise ReleaseError(f"{root}: data/{STORE_REFS} does not give the byte ranges of data/{STORE_ZIP}'s members")
    report["seconds"] = time.perf_counter() - t0
    return report


def check_store_zip(path: str | Path, n_models: int | None = None) -> dict:
    """Check a store zip in place (:func:`store_zip_problems`), then read its first and last model through
    zarr; raise ReleaseError naming every problem.  n_models: the count it must hold (None: not checked)."""
    from spinecohort.release.reader import open_store, read_model_from

    path = Path(path)
    if not path.is_file():
        raise ReleaseError(f"{path}: the store zip is missing")
    problems = store_zip_problems(path)
    if problems:
        raise ReleaseError(f"{path}: the store does not verify:\n  " + "\n  ".join(problems))
    root = open_store(path)
    total = int(root.attrs["n_models"])
    if n_models is not None and n_models != total:
        raise ReleaseError(f"{path}: holds {total} models, {FILES_RECORD} says {n_models}")
    for i in (0, total - 1):
        tri, hexa = read_model_from(root, i)
        if not (np.isfinite(tri).all() and np.isfinite(hexa).all()):
            raise ReleaseError(f"{path}: model {i} has non-finite coordinates")
    return {"models": total, "shards": int(root.attrs["n_shards"]), "store_bytes": path.stat().st_size}


def _describe_bagit(d) -> str:
    import bagit

    if isinstance(d, bagit.ChecksumMismatch):
        return f"{d.path}: {d.algorithm} checksum mismatch (manifest {d.expected}, file {d.found})"
    if isinstance(d, bagit.FileMissing):
        return f"{d.path}: listed in the manifest but missing"
    if isinstance(d, bagit.UnexpectedFile):
        return f"{d.path}: in the bag but not in the manifest (extra file)"
    return str(d)


# ------------------------------------------------------------------------------- export from a bag
def release_model_inputs(release: str | Path) -> dict:
    """Paths and settings ``spinecohort export`` needs, from a release directory (the bag or its
    ``data/``): ssm, hex_ssm, template, faces (.npy), and from ``release.json`` the grid, the hex type and
    the ``fe`` materials the release's decks were written with (None: the package defaults)."""
    root = Path(release)
    data = root / "data" if (root / "data" / RELEASE_JSON).is_file() else root
    rj = data / RELEASE_JSON
    if not rj.is_file():
        raise ReleaseError(
            f"{root}: no {RELEASE_JSON} (neither {root}/data/{RELEASE_JSON} nor {rj}); is this a spinecohort release?"
        )
    info = json.loads(rj.read_text())
    paths = {
        k: data / MODEL_INPUTS / f
        for k, f in (
            ("ssm", "ssm.npz"),
            ("hex_ssm", "hex_ssm.npz"),
            ("template", "template.npz"),
            ("faces", "faces.npy"),
        )
    }
    for k, p in paths.items():
        if not p.is_file():
            raise ReleaseError(f"{p}: missing from the release ({k})")
    return {
        **paths,
        "grid": {"n_modes": info["n_modes"], "levels": info["levels"]},
        "hex_type": info["hex_type"],
        "fe": info.get("fe"),
    }
