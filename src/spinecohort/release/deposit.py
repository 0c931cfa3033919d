"""The deposit: the bag as the flat file list a data repository takes (Zenodo: at most 100 files and 50 GB
per record), and its check after download.

    cohort.zarr.zip        the store, byte for byte the bag's data/cohort.zarr.zip: readers open it in place
    cohort.zarr.refs.json  its members' byte ranges (data/cohort.zarr.refs.json): HTTP readers fetch a chunk
    bag.zip                every other file of the bag, at its path in the bag (deflated)
    README.md              the data README (data/README.md), shown on the record's page

Put back together (``bag.zip`` unpacked, ``cohort.zarr.zip`` moved into its ``data/``) it is the bag again,
and ``spinecohort verify`` checks every sha256 of it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import zipfile
from pathlib import Path

from spinecohort.release.archive import safe_extract, write_zip
from spinecohort.release.names import BAG_ZIP, STORE_REFS, STORE_ZIP, ReleaseError
from spinecohort.release.verify import verify_release

DEPOSIT_FILES = (STORE_ZIP, STORE_REFS, BAG_ZIP, "README.md")


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard link when on the same file system (the store zip is GBs), else a copy."""
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def make_deposit(bag: str | Path, out: str | Path) -> list[Path]:
    """Write the deposit's flat files for ``bag`` into the folder ``out``; returns their paths."""
    bag, out = Path(bag), Path(out)
    store = bag / "data" / STORE_ZIP
    if not store.is_file():
        raise ReleaseError(f"{bag}: no data/{STORE_ZIP}; is it a spinecohort release bag?")
    out.mkdir(parents=True, exist_ok=True)
    members = sorted(p.relative_to(bag).as_posix() for p in bag.rglob("*") if p.is_file() and p != store)
    write_zip(out / BAG_ZIP, bag, members, compress=zipfile.ZIP_DEFLATED)
    _link_or_copy(store, out / STORE_ZIP)
    shutil.copyfile(bag / "data" / STORE_REFS, out / STORE_REFS)
    shutil.copyfile(bag / "data" / "README.md", out / "README.md")
    return [out / f for f in DEPOSIT_FILES]


def verify_deposit(folder: str | Path, processes: int = 1, workdir=None) -> dict:
    """Check a downloaded deposit: ``bag.zip`` unpacked into a temporary folder (under ``workdir``), the
    store zip linked into its ``data/``, then :func:`verify_release` on the bag put back together."""
    folder = Path(folder)
    missing = [f for f in DEPOSIT_FILES if not (folder / f).is_file()]
    if missing:
        raise ReleaseError(f"{folder}: deposit files missing: {', '.join(missing)}")
    with tempfile.TemporaryDirectory(prefix="spinecohort-deposit-", dir=workdir) as tmp:
        bag = Path(tmp) / "bag"
        safe_extract(folder / BAG_ZIP, bag)
        if (bag / "data" / STORE_ZIP).exists():
            raise ReleaseError(f"{folder / BAG_ZIP}: holds data/{STORE_ZIP} itself; not a spinecohort deposit")
        _link_or_copy(folder / STORE_ZIP, bag / "data" / STORE_ZIP)
        for name in (STORE_REFS, "README.md"):  # the loose copies must be the bag's (whose sha256 are checked)
            if (folder / name).read_bytes() != (bag / "data" / name).read_bytes():
                raise ReleaseError(f"{folder / name}: differs from data/{name} in {BAG_ZIP}")
        return verify_release(bag, processes=processes)
