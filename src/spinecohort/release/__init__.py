"""The release: what a data user downloads or reads in place, as a BagIt bag (RFC 8493) checked end to end.

Layout of ``results/<release.dir>/`` (docs/howto/release.md)::

    bagit.txt  bag-info.txt  manifest-sha256.txt  tagmanifest-sha256.txt
    metadata/datacite.json                 DataCite Metadata Schema 4.5 record (validated against the schema)
    metadata/zenodo.json                   the same in Zenodo's deposit metadata format (a ``.zenodo.json``)
    metadata/files.json                    every payload file (key, size, sha256) and the cohort counts
    data/README.md                         for data users: find, read (locally or over HTTP) and export a model
    data/cohort.zarr.zip                   the store as one uncompressed zip: a Zarr v3 zip store, read in place
    data/cohort.zarr.refs.json             its members' byte ranges (fsspec references): exact HTTP range reads
    data/Mean_Model (Template).inp, data/Descriptive_List.xlsx, data/virtual_cohort.csv
    data/patients/*.stl, data/personalized/*.inp, data/figures/**.png
    data/model_inputs/                     SSM, hex SSM, template, faces, grid: what ``export`` needs

Modules: :mod:`names` (file names, safe names), :mod:`archive` (the store zip, reproducible and safely
extracted zips), :mod:`metadata` (DataCite, Zenodo, README), :mod:`build` (the bag), :mod:`verify`,
:mod:`deposit` (the flat file list a repository takes), :mod:`reader` (open the store anywhere, read a
model), :mod:`remote` (a release at a URL: export and the platform without downloading it).
"""

from spinecohort.release.archive import (
    safe_extract,
    store_files,
    store_zip_problems,
    write_references,
    write_store_zip,
    write_zip,
    zip_references,
)
from spinecohort.release.build import build_release, payload_layout, release_counts
from spinecohort.release.deposit import make_deposit, verify_deposit
from spinecohort.release.metadata import (
    datacite_record,
    files_record,
    render_readme,
    validate_datacite,
    zenodo_record,
)
from spinecohort.release.names import (
    BAG_ZIP,
    DATACITE,
    FILES_RECORD,
    MODEL_INPUTS,
    RELEASE_JSON,
    STORE_NAME,
    STORE_REFS,
    STORE_ZIP,
    ZENODO,
    ReleaseError,
    release_dir,
    safe_name,
    safe_relpath,
)
from spinecohort.release.reader import is_url, open_store, read_model_from
from spinecohort.release.verify import check_store_zip, release_model_inputs, verify_release

__all__ = [
    "BAG_ZIP",
    "DATACITE",
    "FILES_RECORD",
    "MODEL_INPUTS",
    "RELEASE_JSON",
    "STORE_NAME",
    "STORE_REFS",
    "STORE_ZIP",
    "ZENODO",
    "ReleaseError",
    "build_release",
    "check_store_zip",
    "datacite_record",
    "files_record",
    "is_url",
    "make_deposit",
    "open_store",
    "payload_layout",
    "read_model_from",
    "release_counts",
    "release_dir",
    "release_model_inputs",
    "render_readme",
    "safe_extract",
    "safe_name",
    "safe_relpath",
    "store_files",
    "store_zip_problems",
    "validate_datacite",
    "verify_deposit",
    "verify_release",
    "write_references",
    "write_store_zip",
    "write_zip",
    "zenodo_record",
    "zip_references",
]
