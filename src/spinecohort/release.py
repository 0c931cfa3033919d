"""The release: what a data user downloads, as a BagIt bag (RFC 8493) checked end to end.

Layout of ``results/<release.dir>/`` (docs/release.md)::

    bagit.txt  bag-info.txt  manifest-sha256.txt  tagmanifest-sha256.txt
    metadata/datacite.json                 DataCite Metadata Schema 4.5 record (validated against the schema)
    metadata/zenodo.json                   the same in Zenodo's deposit metadata format (a ``.zenodo.json``)
    metadata/files.json                    every payload file (key, size, sha256) and the cohort counts
    data/README.md                         for data users: find, read and materialize a model
    data/cohort.zarr.partNNN.tar           the store's files, whole shards per part (uncompressed tar)
    data/cohort.zarr.parts.csv             which shards and model IDs each part holds
    data/Mean_Model (Template).inp, data/Descriptive_List.xlsx, data/virtual_cohort.csv
    data/patients/*.stl, data/personalized/*.inp, data/figures/**.png
    data/model_inputs/                     SSM, hex SSM, template, faces, grid: what ``export`` needs

The bag is made and validated with the Library of Congress ``bagit`` package.  Why the pieces look as
they do:

* Archives are plain tar: the zarr chunks are already zstd-compressed, so a second compression gains
  little (docs/release.md has the measurement) and would make parts slower to open.  They are
  reproducible: members sorted, fixed mtime/mode/owner, PAX format, no directory entries.
* A part holds whole shards (both point arrays, weights chunk and checksum sidecar), so any one part
  unpacks to complete, checkable shards; part 1 also holds the store's metadata.
* Extraction accepts only regular files (and directories) whose names stay inside the destination;
  links, devices, absolute names and ``..`` are refused before anything is written.
* The bag is built in a hidden sibling directory and renamed into place only after it verified, so a
  killed build never leaves a bag that looks complete.
"""

from __future__ import annotations

import csv
import datetime as _dt
import io
import json
import logging
import os
import re
import shutil
import string
import tarfile
import tempfile
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path, PurePosixPath

import numpy as np

log = logging.getLogger(__name__)

#: Name of the store inside the archives and of the archive parts (``cohort.zarr.part001.tar``).
STORE_NAME = "cohort.zarr"
PARTS_INDEX = f"{STORE_NAME}.parts.csv"
DATACITE = "metadata/datacite.json"
ZENODO = "metadata/zenodo.json"
FILES_RECORD = "metadata/files.json"
#: the DataCite Metadata Schema 4.5 as JSON Schema (package data; provenance and licence beside it)
DATACITE_SCHEMA = "data/datacite-v4.5.json"
MODEL_INPUTS = "model_inputs"
RELEASE_JSON = f"{MODEL_INPUTS}/release.json"
#: 2000-01-01T00:00:00Z: a fixed member mtime (some tools treat 0 as "unknown").
ARCHIVE_MTIME = 946684800
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_SHARD_FILE = re.compile(r"^(?:(?:tri/points|hex/volume_points)/c/(\d+)/|weights/c/(\d+)/|checksums/shard_(\d+)/)")
_CTRL = re.compile(r"[\x00-\x1f\x7f\\]")


class ReleaseError(ValueError):
    """The release cannot be built or does not verify; the message names the file and the problem."""


# ------------------------------------------------------------------------------------------ names
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


# --------------------------------------------------------------------------------------- archives
@dataclass(frozen=True)
class Part:
    """One archive part: its file name, the store files it holds (relative, sorted) and their bytes."""

    name: str
    members: tuple[str, ...]
    shards: tuple[int, ...]
    nbytes: int


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


def plan_parts(store: str | Path, part_bytes: int) -> list[Part]:
    """Group the store's files into archive parts of at most ``part_bytes`` (whole shards per part; a
    shard larger than a part gets a part of its own).  Part 1 starts with the store metadata."""
    if part_bytes < 1:
        raise ReleaseError(f"part size must be >= 1 byte, got {part_bytes}")
    root = Path(store)
    units: dict[int, list[str]] = {}
    meta: list[str] = []
    for rel in store_files(root):
        m = _SHARD_FILE.match(rel)
        if m is None:
            meta.append(rel)
        else:
            units.setdefault(int(next(g for g in m.groups() if g is not None)), []).append(rel)
    if not units:
        raise ReleaseError(f"{root}: the store holds no shard; run the pipeline first")
    size = {rel: (root / rel).stat().st_size for rels in [meta, *units.values()] for rel in rels}
    groups: list[tuple[list[int], list[str]]] = [([], list(meta))]
    for shard in sorted(units):
        shards, members = groups[-1]
        add = sum(size[r] for r in units[shard])
        if shards and sum(size[r] for r in members) + add > part_bytes:
            groups.append(([], []))
            shards, members = groups[-1]
        shards.append(shard)
        members.extend(units[shard])
    width = max(3, len(str(len(groups))))
    return [
        Part(
            f"{STORE_NAME}.part{k + 1:0{width}d}.tar",
            tuple(sorted(members)),
            tuple(shards),
            sum(size[r] for r in members),
        )
        for k, (shards, members) in enumerate(groups)
    ]


def write_archive(path: str | Path, root: str | Path, members, prefix: str = STORE_NAME) -> Path:
    """Write an uncompressed, reproducible tar of ``root/member`` files named ``prefix/member``.

    Same files -> byte-identical archive: members in the given (sorted) order, PAX format, mtime
    ARCHIVE_MTIME, mode 0644, uid/gid 0, empty owner names, no directory entries.
    """
    root = Path(root)
    with (
        open(path, "wb") as fh,
        tarfile.open(fileobj=fh, mode="w", format=tarfile.PAX_FORMAT, encoding="utf-8", copybufsize=8 << 20) as tar,
    ):
        for rel in members:
            src = root / safe_relpath(rel, f"archive member of {path}")
            info = tarfile.TarInfo(f"{prefix}/{rel}")
            info.size = src.stat().st_size
            info.mtime, info.mode, info.type = ARCHIVE_MTIME, 0o644, tarfile.REGTYPE
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            with open(src, "rb") as f:
                tar.addfile(info, f)
    return Path(path)


def _check_member(archive: Path, m: tarfile.TarInfo, dest: Path) -> None:
    if not (m.isfile() or m.isdir()):
        kind = "symlink" if m.issym() else "hard link" if m.islnk() else "device or special file"
        raise ReleaseError(f"{archive}: member {m.name!r} is a {kind}; only regular files are allowed")
    try:
        safe_relpath(m.name.rstrip("/") if m.isdir() else m.name, "member")
    except ReleaseError:
        raise ReleaseError(
            f"{archive}: member {m.name!r} would be written outside the extraction directory (absolute name or '..')"
        ) from None
    target = (dest / m.name).resolve()
    if not target.is_relative_to(dest.resolve()):
        raise ReleaseError(f"{archive}: member {m.name!r} resolves to {target}, outside {dest}")


def safe_extract(archive: str | Path, dest: str | Path) -> list[str]:
    """Unpack an uncompressed tar into ``dest``; returns the member names.

    Every member is checked before anything is written: only regular files and directories, names
    relative and without ``..``, resolving inside ``dest``.  Extraction then also runs under tarfile's
    ``data`` filter.  A truncated or corrupt archive raises ReleaseError naming it.
    """
    archive, dest = Path(archive), Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    try:
        with tarfile.open(archive, mode="r:") as tar:
            members = tar.getmembers()
            for m in members:
                _check_member(archive, m, dest)
            tar.extractall(dest, members=members, filter="data")
    except (tarfile.TarError, EOFError) as exc:
        raise ReleaseError(f"{archive}: not a complete tar archive ({exc})") from None
    return [m.name for m in members]


# -------------------------------------------------------------------------------------- payload
def payload_layout(
    results: str | Path,
    *,
    template_inp,
    workbook,
    virtual_csv,
    patient_table,
    patients,
    personalized,
    figures,
    model_inputs: dict,
) -> dict[str, Path]:
    """Where each release input goes inside ``data/`` (relative POSIX path -> source file).

    Files keep their base names (patients under ``patients/``, personalized models under
    ``personalized/``); figures keep their path below ``results`` (without a leading ``figures/``).
    Two inputs landing on the same name is an error, not a silent overwrite.
    """
    results = Path(results)
    out: dict[str, Path] = {}

    def put(rel: str, src) -> None:
        safe_relpath(rel, f"release name of {src}")
        if rel in out and Path(out[rel]) != Path(src):
            raise ReleaseError(f"release name {rel!r} given twice: {out[rel]} and {src}")
        out[rel] = Path(src)

    put(Path(template_inp).name, template_inp)
    put(Path(workbook).name, workbook)
    put(Path(virtual_csv).name, virtual_csv)
    put(f"patients/{Path(patient_table).name}", patient_table)
    for p in patients:
        put(f"patients/{Path(p).name}", p)
    for p in personalized:
        put(f"personalized/{Path(p).name}", p)
    for p in figures:
        p = Path(p)
        try:
            rel = p.relative_to(results).as_posix()
        except ValueError:
            rel = p.name
        put(f"figures/{rel.removeprefix('figures/')}", p)
    for name, p in model_inputs.items():
        put(f"{MODEL_INPUTS}/{name}", p)
    return dict(sorted(out.items()))


def release_counts(
    store: str | Path, template_npz: str | Path, *, n_patients: int, n_personalized: int, n_figures: int, hex_type: str
) -> dict:
    """What the release holds, in numbers (recorded in files.json, datacite.json, release.json and the README)."""
    from spinecohort.store.zarr_store import _open_meta, model_id

    root, meta = _open_meta(store)
    n_tri, n_hex = int(root["tri/points"].shape[1]), int(meta["n_hex_nodes"])
    with np.load(template_npz, allow_pickle=False) as z:
        n_hex_elements = int(z["hexes"].shape[0])
    levels = [float(v) for v in meta["levels"]]
    mean_id = None
    if 0.0 in levels:  # the all-zero (mean) model, when the grid has it
        mean_id = int(model_id(np.zeros(meta["n_modes"]), levels))
    return {
        "n_models": int(meta["n_models"]),
        "n_modes": int(meta["n_modes"]),
        "levels": levels,
        "shard_models": int(meta["shard_models"]),
        "n_shards": int(meta["n_shards"]),
        "n_tri_nodes": n_tri,
        "n_hex_nodes": n_hex,
        "n_hex_elements": n_hex_elements,
        "n_nodes_stored": int(meta["n_models"]) * (n_tri + n_hex),
        "n_patients": int(n_patients),
        "n_personalized": int(n_personalized),
        "n_figures": int(n_figures),
        "hex_type": hex_type,
        "units": "mm",
        "encoding": meta["encoding"],
        "error_bound_mm": float(meta["error_bound_mm"]),
        "mean_model_id": mean_id,
    }


def render_readme(values: dict) -> str:
    """The data user's README (package data ``release_README.md``) with ``$name`` fields filled in."""
    text = resources.files("spinecohort").joinpath("data/release_README.md").read_text(encoding="utf-8")
    return string.Template(text).substitute(values)


def _parts_index(parts: list[Part], shard_models: int, n_models: int) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["part", "first_shard", "last_shard", "first_model", "last_model", "members", "member_bytes"])
    for p in parts:
        lo, hi = min(p.shards), max(p.shards)
        w.writerow(
            [
                p.name,
                lo,
                hi,
                f"model_{lo * shard_models:05d}",
                f"model_{min((hi + 1) * shard_models, n_models) - 1:05d}",
                len(p.members),
                p.nbytes,
            ]
        )
    return buf.getvalue()


def datacite_record(meta: dict, files: list[dict], counts: dict, date: str) -> dict:
    """DataCite Metadata Schema 4.5 record (JSON, the attributes of a DataCite DOI) of the release.

    ``files`` (key, size, checksum) give only the totals and formats: per-file sizes and checksums live in
    the bag's manifests and ``metadata/files.json`` (DataCite has no per-file keys).  Validates against
    the DataCite 4.5 JSON Schema (:func:`validate_datacite`)."""
    creators = []
    for c in meta["creators"]:
        entry = {"name": c["name"], "nameType": "Personal" if "," in c["name"] else "Organizational"}
        if entry["nameType"] == "Personal":
            family, given = (part.strip() for part in c["name"].split(",", 1))
            entry.update(familyName=family, givenName=given)
        if c.get("affiliation"):
            entry["affiliation"] = [{"name": c["affiliation"]}]
        if c.get("orcid"):
            entry["nameIdentifiers"] = [
                {
                    "nameIdentifier": f"https://orcid.org/{c['orcid']}",
                    "nameIdentifierScheme": "ORCID",
                    "schemeUri": "https://orcid.org",
                }
            ]
        creators.append(entry)
    total = sum(f["size"] for f in files)
    return {
        "schemaVersion": "http://datacite.org/schema/kernel-4",
        "types": {"resourceTypeGeneral": "Dataset", "resourceType": "Finite element models (virtual cohort)"},
        "titles": [{"title": meta["title"]}],
        "creators": creators,
        "publisher": {"name": meta["publisher"]},
        "publicationYear": date[:4],
        "dates": [{"date": date, "dateType": "Issued"}],
        "version": meta["version"],
        "language": "en",
        "rightsList": [
            {
                "rights": meta["licence"],
                "rightsIdentifier": meta["licence"].lower(),
                "rightsIdentifierScheme": "SPDX",
                "schemeUri": "https://spdx.org/licenses/",
                "rightsUri": f"https://spdx.org/licenses/{meta['licence']}.html",
            }
        ],
        "descriptions": [
            {"description": meta["description"], "descriptionType": "Abstract"},
            {"description": _technical_info(counts), "descriptionType": "TechnicalInfo"},
        ],
        "subjects": [{"subject": k} for k in meta["keywords"]],
        "sizes": [f"{total} bytes", f"{len(files)} files", f"{counts['n_models']} models"],
        "formats": sorted({_FORMATS.get(Path(f["key"]).suffix, "application/octet-stream") for f in files}),
    }


def _technical_info(counts: dict) -> str:
    return (
        f"{counts['n_models']} virtual models ({counts['n_hex_nodes']} FE nodes and "
        f"{counts['n_tri_nodes']} surface vertices each, mm) in a sharded Zarr v3 store (core codecs only) "
        f"split into {counts['n_parts']} tar parts; {counts['n_patients']} patient "
        f"surfaces; {counts['n_personalized']} personalized models. Packaged as a "
        f"BagIt bag (RFC 8493); see data/README.md. Decks: one connected FE body each (connector springs join "
        f"arches, sacrum, pelvis and femoral heads; facet joints as compression-only contact springs; annulus C3D8R "
        f"with its collagen fibres as tension-only springs tied inside each hexahedron (where the cartilage endplate "
        f"covers only the central endplate, the annulus' insertion into the bony rim, D_<disc>_RIM, C3D8, with its "
        f"fibres), nucleus C3D20R tied to its "
        f"neighbours by *EQUATION); fix node set PELVIS and load the top. Version 0.x renumbers elements (hexahedra "
        f"of bone and endplates first, then annulus and nucleus; the fibre springs last) and appends the facet-joint "
        f"nodes, the nucleus' midside nodes and the fibre springs' end nodes after the template's nodes 1..N."
    )


def zenodo_record(meta: dict, counts: dict, date: str) -> dict:
    """The release in Zenodo's deposit metadata format (the ``metadata`` of a deposit, as in a
    ``.zenodo.json``): upload type dataset, open access, the licence as Zenodo's lower-case SPDX id.
    Zenodo's deposit schema has no ``version`` key (its web form does): the version is in ``notes``."""
    creators = []
    for c in meta["creators"]:
        entry = {"name": c["name"]}
        if c.get("affiliation"):
            entry["affiliation"] = c["affiliation"]
        if c.get("orcid"):
            entry["orcid"] = c["orcid"]
        creators.append(entry)
    return {
        "upload_type": "dataset",
        "title": meta["title"],
        "creators": creators,
        "description": meta["description"],
        "notes": f"Version {meta['version']}. " + _technical_info(counts),
        "publication_date": date,
        "access_right": "open",
        "license": meta["licence"].lower(),
        "keywords": list(meta["keywords"]),
    }


def files_record(files: list[dict], counts: dict) -> dict:
    """Every payload file (key, size in bytes, ``sha256:`` checksum) and the cohort counts: what
    ``verify`` checks sizes and counts against (the sha256 are also in manifest-sha256.txt)."""
    return {"files": files, "counts": counts}


def validate_datacite(record: dict) -> None:
    """Raise ReleaseError unless ``record`` validates against the DataCite 4.5 JSON Schema."""
    import jsonschema

    schema = json.loads(resources.files("spinecohort").joinpath(DATACITE_SCHEMA).read_text(encoding="utf-8"))
    validator = jsonschema.validators.validator_for(schema)(schema)
    errors = sorted(validator.iter_errors(record), key=lambda e: list(e.absolute_path))
    if errors:
        lines = "; ".join(f"{'/'.join(map(str, e.absolute_path)) or '(root)'}: {e.message}" for e in errors[:5])
        raise ReleaseError(f"{DATACITE} does not validate against the DataCite 4.5 schema: {lines}")


_FORMATS = {
    ".tar": "application/x-tar",
    ".inp": "text/plain (Abaqus/CalculiX input deck)",
    ".xlsx": "application/vnd.openxmlformats-officedocument.spreadsheetml.sheet",
    ".csv": "text/csv",
    ".stl": "model/stl",
    ".png": "image/png",
    ".md": "text/markdown",
    ".npz": "application/x-npz (NumPy)",
    ".npy": "application/x-npy (NumPy)",
    ".json": "application/json",
}


def _bag_info(meta: dict, date: str, counts: dict) -> dict:
    import bagit

    from spinecohort import __version__

    first = meta["creators"][0]["name"]
    return {
        "Source-Organization": meta["publisher"],
        "Contact-Name": first,
        "External-Description": meta["description"],
        "External-Identifier": f"spinecohort-release-{meta['version']}",
        "Bagging-Date": date,
        "Bag-Software-Agent": f"spinecohort {__version__} with bagit.py {bagit.VERSION}",
        "Title": meta["title"],
        "Version": meta["version"],
        "License": meta["licence"],
        "Creator": [c["name"] for c in meta["creators"]],
        "Models": str(counts["n_models"]),
    }


# ------------------------------------------------------------------------------------------ build
def _copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)  # content only: the bag's files get ordinary permissions, not 0600


def build_release(
    out: str | Path,
    *,
    store: str | Path,
    files: dict[str, Path],
    meta: dict,
    counts: dict,
    readme_values: dict | None = None,
    generated: dict[str, bytes] | None = None,
    model_settings: dict | None = None,
    processes: int = 1,
    verify: bool = True,
) -> dict:
    """Build the bag at ``out`` (atomically) and return a summary (files, bytes, parts, seconds).

    store: the cohort store (must pass ``check_store``).  files: ``payload_layout`` output; generated:
    further payload files given by content (relative path -> bytes).  meta: the ``release`` config block.
    model_settings: what ``export`` needs besides the files (e.g. the ``fe`` materials), kept in release.json.  counts: model/node counts recorded in files.json and datacite.json.  The bag is built in
    ``.<name>.tmp-<pid>`` next to ``out``, verified (unless verify=False), then renamed to ``out``.
    """
    import bagit

    from spinecohort.store.zarr_store import check_store

    out = Path(out)
    safe_name(out.name, "release directory")
    if out.is_symlink():
        raise ReleaseError(f"{out} is a symlink; refusing to write the release through it")
    bad = check_store(store)
    if bad:
        raise ReleaseError(f"{store}: shards {bad} are missing or fail their checksums; rebuild them first")
    t0 = time.perf_counter()
    date = meta.get("date") or _dt.date.today().isoformat()
    out.parent.mkdir(parents=True, exist_ok=True)
    for stale in out.parent.glob(f".{out.name}.tmp-*"):  # a killed earlier build
        shutil.rmtree(stale, ignore_errors=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    tmp.mkdir()
    try:
        for rel, src in files.items():
            _copy(Path(src), tmp / rel)
        for rel, content in (generated or {}).items():
            (tmp / safe_relpath(rel)).parent.mkdir(parents=True, exist_ok=True)
            (tmp / rel).write_bytes(content)
        parts = plan_parts(store, int(meta["part_size_mb"] * 1e6))
        for p in parts:
            write_archive(tmp / p.name, store, p.members)
        counts = {**counts, "n_parts": len(parts)}
        (tmp / PARTS_INDEX).write_text(_parts_index(parts, counts["shard_models"], counts["n_models"]))
        release_json = {
            "version": meta["version"],
            "title": meta["title"],
            "store": STORE_NAME,
            "parts": [p.name for p in parts],
            **counts,
            **(model_settings or {}),
        }
        (tmp / RELEASE_JSON).parent.mkdir(parents=True, exist_ok=True)
        (tmp / RELEASE_JSON).write_text(json.dumps(release_json, indent=2, sort_keys=True) + "\n")
        sm, nm = counts["shard_models"], counts["n_models"]
        parts_table = "\n".join(
            f"| `{p.name}` | model_{min(p.shards) * sm:05d} – model_{min((max(p.shards) + 1) * sm, nm) - 1:05d} "
            f"| {p.nbytes / 1e6:.1f} MB |"
            for p in parts
        )
        mean = counts.get("mean_model_id")
        (tmp / "README.md").write_text(
            render_readme(
                {
                    **counts,
                    **(readme_values or {}),
                    "title": meta["title"],
                    "version": meta["version"],
                    "licence": meta["licence"],
                    "parts_table": parts_table,
                    "n_levels": len(counts["levels"]),
                    "levels": "{" + ", ".join(f"{v:g}" for v in counts["levels"]) + "}",
                    "mean_model": f"model_{mean:05d}" if mean is not None else "model_00000",
                }
            )
        )
        t_payload = time.perf_counter()
        log.info(
            "payload: %d files + %d archive parts (%.1f MB of store files) in %.1f s",
            len(files),
            len(parts),
            sum(p.nbytes for p in parts) / 1e6,
            t_payload - t0,
        )
        bagit.make_bag(str(tmp), _bag_info(meta, date, counts), processes=processes, checksums=["sha256"])
        # bagit.py 1.9 still stamps the draft version 0.97 (LibraryOfCongress/bagit-python#141); what it
        # writes (manifests, percent-encoded names, tag manifest, bag-info) is what RFC 8493 specifies
        (tmp / "bagit.txt").write_text("BagIt-Version: 1.0\nTag-File-Character-Encoding: UTF-8\n")
        bag = bagit.Bag(str(tmp))
        entries = bag.payload_entries()
        file_list = [
            {"key": k, "size": (tmp / k).stat().st_size, "checksum": f"sha256:{entries[k]['sha256']}"}
            for k in sorted(entries)
        ]
        (tmp / DATACITE).parent.mkdir()
        datacite = datacite_record(meta, file_list, counts, date)
        validate_datacite(datacite)
        for name, record in (
            (DATACITE, datacite),
            (ZENODO, zenodo_record(meta, counts, date)),
            (FILES_RECORD, files_record(file_list, counts)),
        ):
            (tmp / name).write_text(json.dumps(record, indent=2) + "\n")
        bag.save()  # rewrites bag-info.txt and the tag manifest, now covering metadata/*.json
        _sort_tagmanifest(tmp / "tagmanifest-sha256.txt")
        t_bag = time.perf_counter()
        log.info("bag made (sha256 of %d files) in %.1f s", len(file_list), t_bag - t_payload)
        report = verify_release(tmp, processes=processes) if verify else {}
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            out.rename(old)
            tmp.rename(out)
            shutil.rmtree(old)
        else:
            tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {
        "files": len(file_list),
        "bytes": sum(f["size"] for f in file_list),
        "parts": len(parts),
        "seconds_payload": t_payload - t0,
        "seconds_bag": t_bag - t_payload,
        "seconds_verify": report.get("seconds", 0.0),
        "seconds": time.perf_counter() - t0,
    }


def _sort_tagmanifest(path: Path) -> None:
    """bagit.py lists tag files in directory order, one space after the digest: sort them (same bag
    from the same inputs -> same bytes) and use two spaces, so ``sha256sum -c`` reads it too."""
    lines = [ln.split(maxsplit=1) for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    path.write_text("".join(f"{d}  {f}\n" for d, f in sorted(lines, key=lambda x: x[1])), encoding="utf-8")


# ----------------------------------------------------------------------------------------- verify
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


def verify_release(
    bag_dir: str | Path, processes: int = 1, unpack: bool = True, workdir: str | Path | None = None
) -> dict:
    """Check a release bag; raise ReleaseError listing every problem found.

    1. BagIt: no file missing, no extra file (payload and tag files), every size as recorded in
       metadata/files.json, every sha256 in the manifests (``bagit.Bag.validate``).
    2. unpack=True: every archive part unpacks (safely) into a temporary directory under ``workdir``
       (default: the system's), to exactly the members the parts index lists, and the unpacked store
       passes ``check_store`` and reads its first and last model.
    Returns counts and the time taken.
    """
    import bagit

    from spinecohort.store.zarr_store import check_store, read_model

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
    if unpack:
        data = root / "data"
        index = list(csv.DictReader((data / PARTS_INDEX).open())) if (data / PARTS_INDEX).is_file() else None
        if index is None:
            raise ReleaseError(f"{root}: data/{PARTS_INDEX} is missing")
        listed = [row["part"] for row in index]
        on_disk = sorted(p.name for p in data.glob(f"{STORE_NAME}.part*.tar"))
        if sorted(listed) != on_disk:
            raise ReleaseError(f"{root}: archive parts {on_disk} differ from data/{PARTS_INDEX} ({listed})")
        # the parts hold the whole store (8 GB on the default grid): say so before a full disk interrupts tar
        need = sum((data / row["part"]).stat().st_size for row in index)
        where = Path(workdir) if workdir is not None else Path(tempfile.gettempdir())
        free = shutil.disk_usage(where).free
        if free < need:
            raise ReleaseError(
                f"{root}: verifying the release unpacks its {len(index)} archive parts ({need / 1e9:.2f} GB) into "
                f"{where}, which has {free / 1e9:.2f} GB free; free space there or unpack elsewhere (TMPDIR, or "
                "`spinecohort verify --tmpdir DIR`)"
            )
        with tempfile.TemporaryDirectory(prefix="spinecohort-verify-", dir=workdir) as tmp:
            for row in index:
                names = safe_extract(data / row["part"], tmp)
                if len(names) != int(row["members"]):
                    raise ReleaseError(
                        f"data/{row['part']}: {len(names)} members, data/{PARTS_INDEX} lists "
                        f"{row['members']} (truncated archive?)"
                    )
            store = Path(tmp) / STORE_NAME
            try:
                bad = check_store(store)
            except ValueError as exc:
                raise ReleaseError(f"{root}: the archives do not unpack to a cohort store ({exc})") from None
            if bad:
                raise ReleaseError(f"{root}: the unpacked store has missing or corrupt shards {bad}")
            import zarr

            n_models = zarr.open_group(str(store), mode="r").attrs["n_models"]
            for i in (0, n_models - 1):
                tri, hexa = read_model(store, i)
                if not (np.isfinite(tri).all() and np.isfinite(hexa).all()):
                    raise ReleaseError(f"{root}: model {i} of the unpacked store has non-finite coordinates")
            counts = record.get("counts", {})
            if counts and counts.get("n_models") != n_models:
                raise ReleaseError(
                    f"{root}: unpacked store holds {n_models} models, {FILES_RECORD} says {counts.get('n_models')}"
                )
            report.update(parts=len(index), models=int(n_models))
    report["seconds"] = time.perf_counter() - t0
    return report


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
