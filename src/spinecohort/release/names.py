"""Names inside a release: the fixed file names of the bag and the deposit, and the checks that keep a
configured or archived name inside its folder."""

from __future__ import annotations

import re
from pathlib import Path, PurePosixPath

#: Name of the store; in the bag and the deposit it is one uncompressed zip, ``cohort.zarr.zip``.
STORE_NAME = "cohort.zarr"
STORE_ZIP = f"{STORE_NAME}.zip"
#: byte ranges of the store zip's members (fsspec reference spec v1): HTTP readers fetch exactly a chunk
STORE_REFS = f"{STORE_NAME}.refs.json"
DATACITE = "metadata/datacite.json"
ZENODO = "metadata/zenodo.json"
FILES_RECORD = "metadata/files.json"
#: the DataCite Metadata Schema 4.5 as JSON Schema (package data; provenance and licence beside it)
DATACITE_SCHEMA = "data/datacite-v4.5.json"
MODEL_INPUTS = "model_inputs"
RELEASE_JSON = f"{MODEL_INPUTS}/release.json"
#: the deposit's zip of every bag file except the store zip (the bag's folders in one flat file)
BAG_ZIP = "bag.zip"
#: 1980-01-01 00:00:00, the earliest time a zip entry can carry: every member gets it (reproducible zips)
ZIP_DATE_TIME = (1980, 1, 1, 0, 0, 0)
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_CTRL = re.compile(r"[\x00-\x1f\x7f\\]")


class ReleaseError(ValueError):
    """The release cannot be built or does not verify; the message names the file and the problem."""


def safe_name(name: str, what: str = "name") -> str:
    """A configurable file or directory name: one path component of letters, digits, ``._-``, starting
    with a letter or digit (so no ``/``, no absolute path, no ``..``, no hidden file)."""
    if not isinstance(name, str) or not _SAFE_NAME.fullmatch(name):
        raise ReleaseError(
            f"{what} {name!r} must be a plain name (letters, digits, '.', '_', '-'; starting "
            f"with a letter or digit; no '/', no '..', not absolute)"
        )
    return name


def safe_relpath(rel: str, what: str = "path") -> str:
    """A relative POSIX path that stays inside its root: no absolute path, no ``..``/``.``/empty
    component, no backslash or control character.  Returns it unchanged."""
    p = PurePosixPath(rel)
    if (
        not rel
        or rel.startswith("/")
        or p.is_absolute()
        or _CTRL.search(rel)
        or any(part in ("", ".", "..") for part in rel.split("/"))
    ):
        raise ReleaseError(
            f"{what} {rel!r} is not a safe relative path (absolute, '..', '.', empty or control characters)"
        )
    return rel


def release_dir(results: str | Path, name: str) -> Path:
    """``results/name`` after checking that ``name`` is a plain name (it cannot leave ``results``)."""
    return Path(results) / safe_name(name, "release.dir")
