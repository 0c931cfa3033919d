"""The release's metadata: the DataCite 4.5 record, Zenodo's deposit metadata, the file record, the
bag-info fields, and the data user's README."""

from __future__ import annotations

import json
import string
from importlib import resources
from pathlib import Path

from spinecohort.release.names import DATACITE, DATACITE_SCHEMA, STORE_ZIP, ReleaseError


def render_readme(values: dict) -> str:
    """The data user's README (package data ``release_README.md``) with ``$name`` fields filled in."""
    text = resources.files("spinecohort").joinpath("data/release_README.md").read_text(encoding="utf-8")
    return string.Template(text).substitute(values)


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
        f"deposited as one uncompressed zip, {STORE_ZIP}, that Zarr readers open in place over HTTP range "
        f"requests ({counts['chunk_models']} model(s) per chunk); {counts['n_patients']} patient "
        f"surfaces; {counts['n_personalized']} personalized models. Packaged as a "
        f"BagIt bag (RFC 8493); see data/README.md. Decks: one connected FE body each (hexahedral pedicles "
        f"of bone carry each arch on a real-bone cohort; connector springs join arches, sacrum, pelvis and femoral "
        f"heads; facet joints as compression-only contact springs; annulus C3D8R "
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
    ".zip": "application/zip",
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
