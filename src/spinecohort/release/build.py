"""Building the release bag: where each input goes, what the release holds in numbers, and the bag itself
(made, described, verified, then moved into place)."""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import shutil
import time
from pathlib import Path

import numpy as np

from spinecohort.release.archive import write_references, write_store_zip
from spinecohort.release.metadata import (
    _bag_info,
    datacite_record,
    files_record,
    render_readme,
    validate_datacite,
    zenodo_record,
)
from spinecohort.release.names import (
    DATACITE,
    FILES_RECORD,
    MODEL_INPUTS,
    RELEASE_JSON,
    STORE_REFS,
    STORE_ZIP,
    ZENODO,
    ReleaseError,
    safe_name,
    safe_relpath,
)
from spinecohort.release.verify import verify_release

log = logging.getLogger(__name__)


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
        "chunk_models": int(meta["chunk_models"]),
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
    """Build the bag at ``out`` (atomically) and return a summary (files, bytes, store bytes, seconds).

    store: the cohort store (must pass ``check_store``), zipped uncompressed into ``data/cohort.zarr.zip`` with
    its members' byte ranges in ``data/cohort.zarr.refs.json``.  files: ``payload_layout`` output; generated:
    further payload files given by content (relative path -> bytes).  meta: the ``release`` config block.
    model_settings: what ``export`` needs besides the files (e.g. the ``fe`` materials), kept in release.json.
    counts: model/node counts recorded in files.json and datacite.json.  The bag is built in
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
        zipped = write_store_zip(tmp / STORE_ZIP, store)
        write_references(tmp / STORE_REFS, tmp / STORE_ZIP)
        release_json = {
            "version": meta["version"],
            "title": meta["title"],
            "store": STORE_ZIP,
            **counts,
            **(model_settings or {}),
        }
        (tmp / RELEASE_JSON).parent.mkdir(parents=True, exist_ok=True)
        (tmp / RELEASE_JSON).write_text(json.dumps(release_json, indent=2, sort_keys=True) + "\n")
        mean = counts.get("mean_model_id")
        (tmp / "README.md").write_text(
            render_readme(
                {
                    **counts,
                    **(readme_values or {}),
                    "title": meta["title"],
                    "version": meta["version"],
                    "licence": meta["licence"],
                    "store_zip": STORE_ZIP,
                    "store_refs": STORE_REFS,
                    "store_gb": f"{zipped['bytes'] / 1e9:.2f}",
                    "n_levels": len(counts["levels"]),
                    "levels": "{" + ", ".join(f"{v:g}" for v in counts["levels"]) + "}",
                    "mean_model": f"model_{mean:05d}" if mean is not None else "model_00000",
                    "mean_index": mean if mean is not None else 0,
                }
            )
        )
        t_payload = time.perf_counter()
        log.info(
            "payload: %d files + %s (%d store files, %.1f MB) in %.1f s",
            len(files),
            STORE_ZIP,
            zipped["members"],
            zipped["bytes"] / 1e6,
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
        "store_bytes": zipped["bytes"],
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
