"""The release bag (spinecohort.release, rule ``release``): a valid BagIt bag with the store as one
uncompressed zip, verification that names what is wrong, reproducible zips, extraction that cannot escape
its folder, config names that cannot move the release out of ``results``, the flat deposit, and ``export``
from a release."""

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml

from spinecohort.cli import main
from spinecohort.config import ConfigError, validate_config
from spinecohort.release import (
    ReleaseError,
    make_deposit,
    payload_layout,
    release_dir,
    safe_extract,
    verify_deposit,
    verify_release,
    write_zip,
    zip_references,
)

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


@pytest.fixture(scope="module")
def pristine(test_run, tmp_path_factory):
    """A copy of the DAG run's release, taken before any test reruns or corrupts anything."""
    dst = tmp_path_factory.mktemp("pristine") / "release"
    shutil.copytree(test_run / "results" / "release", dst)
    return dst


@pytest.fixture
def bag(pristine, tmp_path):
    """A private copy to corrupt."""
    return Path(shutil.copytree(pristine, tmp_path / "release"))


def test_release_is_a_valid_bag_with_the_whole_payload(pristine):
    # the test config: 27 models in 3 shards of 9, all in one store zip
    rep = verify_release(pristine)
    assert rep["shards"] == 3 and rep["models"] == 27
    assert (pristine / "bagit.txt").read_text().startswith("BagIt-Version: 1.0\n")
    data = pristine / "data"
    names = {p.relative_to(data).as_posix() for p in data.rglob("*") if p.is_file()}
    assert {
        "Mean_Model (Template).inp",
        "Descriptive_List.xlsx",
        "README.md",
        "cohort.zarr.zip",
        "cohort.zarr.refs.json",
        "model_inputs/ssm.npz",
        "model_inputs/faces.npy",
        "figures/mode_variation.png",
    } <= names
    # stored members only (a zarr zip store is read in place), every file of the store folder once
    with zipfile.ZipFile(data / "cohort.zarr.zip") as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
        # 11 zarr.json (root, 7 arrays and groups, 3 shard records), the surface_vertex chunk, 3 shards x 3 objects
        assert len(zf.namelist()) == len(set(zf.namelist())) == 21
    assert len([n for n in names if n.startswith("patients/P")]) == 8  # the 8 test patients
    record = json.loads((pristine / "metadata" / "files.json").read_text())
    assert record["counts"]["n_models"] == 27 and record["counts"]["n_hex_nodes"] == 23028  # coarse template
    assert {f["key"] for f in record["files"]} == {f"data/{n}" for n in names}
    assert all(f["checksum"].startswith("sha256:") and f["size"] > 0 for f in record["files"])
    # peer tool: coreutils reads both manifests (paths with spaces included)
    for manifest in ("manifest-sha256.txt", "tagmanifest-sha256.txt"):
        proc = subprocess.run(["sha256sum", "-c", "--quiet", manifest], cwd=pristine, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stdout + proc.stderr


def _validator(schema_path: Path):
    import jsonschema

    schema = json.loads(schema_path.read_text())
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema, format_checker=cls.FORMAT_CHECKER)


DATACITE_SCHEMA = ROOT / "src" / "spinecohort" / "data" / "datacite-v4.5.json"
ZENODO_SCHEMA = ROOT / "tests" / "data" / "zenodo-legacy-deposit-v1.0.0.json"


def test_datacite_record_validates_against_the_datacite_4_5_schema(pristine):
    """The official DataCite 4.5 JSON Schema (vendored from the `datacite` package): no error, and a record
    with the old per-file keys (files, counts) is rejected, as DataCite rejects unknown keys."""
    record = json.loads((pristine / "metadata" / "datacite.json").read_text())
    v = _validator(DATACITE_SCHEMA)
    assert list(v.iter_errors(record)) == []
    assert record["types"]["resourceTypeGeneral"] == "Dataset" and record["publicationYear"].isdigit()
    assert "27 models" in record["sizes"]
    bad = {**record, "files": [{"key": "data/README.md", "size": 1}], "counts": {"n_models": 27}}
    assert {e.validator for e in v.iter_errors(bad)} == {"additionalProperties"}


def test_zenodo_deposit_metadata_validates_against_zenodos_schema(pristine):
    """Zenodo's own deposit schema (tests/data, from zenodo/zenodo): no error; the same title and version as
    the DataCite record (the schema has no version key: it is in the notes); a wrong upload type is caught."""
    record = json.loads((pristine / "metadata" / "zenodo.json").read_text())
    v = _validator(ZENODO_SCHEMA)
    assert list(v.iter_errors(record)) == []
    datacite = json.loads((pristine / "metadata" / "datacite.json").read_text())
    assert record["title"] == datacite["titles"][0]["title"]
    assert record["notes"].startswith(f"Version {datacite['version']}. ")
    assert record["upload_type"] == "dataset" and record["access_right"] == "open"
    assert [e.validator for e in v.iter_errors({**record, "upload_type": "data set"})] == ["enum"]


def _flip_byte(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_verify_names_a_flipped_byte(bag):
    store = bag / "data" / "cohort.zarr.zip"
    _flip_byte(store, store.stat().st_size // 2)
    with pytest.raises(ReleaseError, match=r"data/cohort.zarr.zip: sha256 checksum mismatch"):
        verify_release(bag)


def test_store_check_names_the_corrupt_shard_object(bag):
    """The store zip's own check (no manifests involved) names the member: a flipped byte inside shard 1's
    tri/points object fails the zip's CRC-32 of that member."""
    from spinecohort.release import check_store_zip

    store = bag / "data" / "cohort.zarr.zip"
    off = zip_references(store)["refs"]["tri/points/c/1/0/0"][1]
    _flip_byte(store, off + 100)
    with pytest.raises(ReleaseError, match=r"tri/points/c/1/0/0 \(shard 1\) is corrupt"):
        check_store_zip(store)


def test_verify_names_a_missing_file(bag):
    (bag / "data" / "patients" / "P03.stl").unlink()
    with pytest.raises(ReleaseError, match=r"data/patients/P03.stl: listed in the manifest but missing"):
        verify_release(bag)


def test_verify_names_extra_files(bag):
    (bag / "data" / "notes.txt").write_text("not part of the release")
    (bag / "metadata" / "extra.json").write_text("{}")
    with pytest.raises(ReleaseError) as err:
        verify_release(bag)
    assert "data/notes.txt: in the bag but not in manifest-sha256.txt (extra file)" in str(err.value)
    assert "metadata/extra.json: in the bag but not in tagmanifest-sha256.txt (extra file)" in str(err.value)


def test_verify_names_a_truncated_store_zip(bag, tmp_path):
    store = bag / "data" / "cohort.zarr.zip"
    full = store.read_bytes()
    store.write_bytes(full[: len(full) // 2])
    with pytest.raises(
        ReleaseError,
        match=rf"data/cohort.zarr.zip: {len(full) // 2} bytes, but "
        rf"metadata/files.json records {len(full)} \(truncated",
    ):
        verify_release(bag)
    # extraction on its own: a zip cut in half has no central directory and is refused by name
    with pytest.raises(ReleaseError, match=r"cohort.zarr.zip: not a complete zip archive"):
        safe_extract(store, tmp_path / "out")


def test_two_release_runs_give_byte_identical_bags(test_run, pristine):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            "-s",
            str(ROOT / "Snakefile"),
            "--directory",
            str(test_run),
            "-j2",
            "--forcerun",
            "release",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    again = test_run / "results" / "release"
    assert "rule release:" in proc.stdout + proc.stderr  # it really ran again
    for f in (
        "manifest-sha256.txt",
        "data/cohort.zarr.zip",
        "data/cohort.zarr.refs.json",
        "data/README.md",
    ):
        assert (again / f).read_bytes() == (pristine / f).read_bytes(), f
    # tag files carry the build date only; same day -> the same bytes too
    if (again / "bag-info.txt").read_text() == (pristine / "bag-info.txt").read_text():
        assert (again / "tagmanifest-sha256.txt").read_bytes() == (pristine / "tagmanifest-sha256.txt").read_bytes()


def test_zips_do_not_depend_on_file_metadata(tmp_path):
    # same bytes, different mtimes and permissions -> identical zips (fixed date, mode, order)
    for k, (mtime, mode) in enumerate([(1_600_000_000, 0o600), (1_700_000_000, 0o644)]):
        root = tmp_path / f"s{k}"
        (root / "c" / "0").mkdir(parents=True)
        for rel, content in (("zarr.json", b"{}"), ("c/0/0", bytes(range(256)) * 12)):
            (root / rel).write_bytes(content)
            os.chmod(root / rel, mode)
            os.utime(root / rel, (mtime, mtime))
        write_zip(tmp_path / f"a{k}.zip", root, ["c/0/0", "zarr.json"])
    assert (tmp_path / "a0.zip").read_bytes() == (tmp_path / "a1.zip").read_bytes()
    with zipfile.ZipFile(tmp_path / "a0.zip") as zf:
        m = zf.infolist()
    assert [x.filename for x in m] == ["c/0/0", "zarr.json"]
    assert {(x.date_time, x.external_attr >> 16, x.compress_type) for x in m} == {
        ((1980, 1, 1, 0, 0, 0), 0o100644, zipfile.ZIP_STORED)
    }
    # the references give each member's bytes: offset 30 + name length (no extra field) past its header
    refs = zip_references(tmp_path / "a0.zip")
    assert refs["refs"]["zarr.json"] == "{}"  # metadata inlined
    _, off, n = refs["refs"]["c/0/0"]
    assert (off, n) == (30 + len("c/0/0"), 3072)
    assert (tmp_path / "a0.zip").read_bytes()[off : off + n] == bytes(range(256)) * 12


def _malicious(path: Path, name: str, symlink: bool = False) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("cohort.zarr/zarr.json", b"{}")  # a harmless member first: nothing may be written at all
        info = zipfile.ZipInfo(name)
        if symlink:
            info.create_system = 3
            info.external_attr = 0o120777 << 16
        zf.writestr(info, b"/etc/passwd" if symlink else b"x")
    return path


@pytest.mark.parametrize(
    "name, symlink, message",
    [
        ("../evil.txt", False, "outside the extraction directory"),
        ("cohort.zarr/../../evil.txt", False, "outside the extraction directory"),
        ("/tmp/spinecohort-evil.txt", False, "outside the extraction directory"),
        ("cohort.zarr/link", True, "is a symlink"),
    ],
)
def test_zip_members_cannot_escape_the_extraction_directory(tmp_path, name, symlink, message):
    archive = _malicious(tmp_path / "bad.zip", name, symlink)
    dest = tmp_path / "out" / "deep"
    with pytest.raises(ReleaseError, match=message) as err:
        safe_extract(archive, dest)
    assert "bad.zip" in str(err.value) and repr(name) in str(err.value)
    assert list(dest.rglob("*")) == []  # checked before anything is written
    assert not (tmp_path / "out" / "evil.txt").exists() and not Path("/tmp/spinecohort-evil.txt").exists()


@pytest.mark.parametrize("name", ["../escape", "/tmp/release", "sub/release", "..", ".hidden", ""])
def test_release_dir_outside_results_is_rejected(name):
    cfg = yaml.safe_load((ROOT / ".test" / "config" / "config.yaml").read_text())
    cfg["release"]["dir"] = name
    with pytest.raises(ConfigError, match=r"release\.dir: .* does not match"):
        validate_config(cfg, SCHEMA)
    with pytest.raises(ReleaseError, match=r"release\.dir .* must be a plain name"):
        release_dir("results", name)  # the second line of defence (rule file, package callers)


def test_bad_release_dir_stops_snakemake_before_any_rule(tmp_path):
    work = tmp_path / "work"
    (work / "config").mkdir(parents=True)
    cfg = yaml.safe_load((ROOT / ".test" / "config" / "config.yaml").read_text())
    cfg["release"]["dir"] = "../outside"
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(cfg))
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory", str(work), "-j1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0 and "release.dir: '../outside' does not match" in proc.stdout + proc.stderr
    assert not (work / "results").exists()
    assert not (tmp_path / "outside").exists()


def test_payload_names_never_collide_silently(tmp_path):
    a, b = tmp_path / "r" / "x" / "fig.png", tmp_path / "r" / "figures" / "x" / "fig.png"
    with pytest.raises(ReleaseError, match="release name 'figures/x/fig.png' given twice"):
        payload_layout(
            tmp_path / "r",
            template_inp="t.inp",
            workbook="w.xlsx",
            virtual_csv="v.csv",
            patient_table="p.csv",
            patients=[],
            personalized=[],
            figures=[a, b],
            model_inputs={},
        )


def test_export_from_an_unpacked_release_equals_export_from_results(test_run, pristine, tmp_path):
    cwd = os.getcwd()
    os.chdir(test_run)  # --config is relative to the work dir, as for a user in their project
    try:
        assert main(["export", "model_00013", "--out", str(tmp_path / "results.inp")]) == 0
    finally:
        os.chdir(cwd)
    assert main(["export", "model_00013", "--release", str(pristine), "--out", str(tmp_path / "release.inp")]) == 0
    assert (tmp_path / "release.inp").read_bytes() == (tmp_path / "results.inp").read_bytes()
    assert main(["export", "model_00013", "--release", str(tmp_path), "--out", str(tmp_path / "x.inp")]) == 2
    # --load: the same model data, then a pure-moment step (2 N.m right lateral bending on L1, pelvis fixed)
    load = tmp_path / "load.inp"
    args = ["export", "model_00013", "--release", str(pristine), "--load", "lateral_right", "--top", "L1"]
    assert main(args + ["--moment-nm", "2", "--out", str(load)]) == 0
    text, plain = load.read_text(), (tmp_path / "release.inp").read_text()
    model_part = text.split("*HEADING")[1].split("** pure moment")[0]

    def node_block(deck: str) -> str:
        return deck.split("*NODE")[1].split("\n*")[0]

    # the same nodes, then T1's potting plate (`spinecohort.fe.potting`) after them; the arches act through their
    # connector truss, so their S3 skins are left out of a load deck
    assert node_block(model_part).startswith(node_block(plain) + "\n")
    assert "*ELSET, ELSET=L1_POTTING\n" in model_part
    assert "POST_" in plain and "POST_" not in model_part
    step = text.split("** pure moment")[1]
    assert "*RIGID BODY, NSET=RB_L1" in step and "*BOUNDARY\nFIXED, 1, 3" in step and "*STEP, NLGEOM" in step
    cload = [float(line.split(",")[2]) for line in step.split("*CLOAD\n")[1].split("*")[0].splitlines()]
    assert sum(c * c for c in cload) ** 0.5 == pytest.approx(2000.0, rel=1e-6)  # N.mm


def test_cli_verify_and_unpack(bag, tmp_path, capsys):
    from spinecohort.store.zarr_store import check_store

    assert main(["verify", str(bag)]) == 0
    assert "the store zip holds 3 intact shards of 27 models" in capsys.readouterr().out
    assert main(["unpack", str(bag), "--to", str(tmp_path / "u")]) == 0
    assert check_store(tmp_path / "u" / "cohort.zarr") == []  # every shard's crc32c sidecar matches
    readme = bag / "data" / "README.md"
    readme.write_bytes(readme.read_bytes().replace(b"# ", b"#!", 1))  # same size: only sha256 can tell
    assert main(["verify", str(bag), "--no-store"]) == 2
    assert "data/README.md: sha256 checksum mismatch" in capsys.readouterr().err


def test_deposit_is_flat_within_zenodos_limits_and_verifies(pristine, tmp_path, capsys):
    """The deposit: 4 flat files (Zenodo: at most 100 files, 50 GB per record), the store zip the bag's own
    bytes; downloaded into a folder, `verify` puts the bag back together and checks every sha256."""
    out = tmp_path / "deposit"
    assert main(["deposit", str(pristine), str(out)]) == 0
    files = sorted(p.name for p in out.iterdir())
    assert files == ["README.md", "bag.zip", "cohort.zarr.refs.json", "cohort.zarr.zip"]
    assert all(p.is_file() and p.stat().st_size < 50e9 for p in out.iterdir())
    assert (out / "cohort.zarr.zip").read_bytes() == (pristine / "data" / "cohort.zarr.zip").read_bytes()
    assert verify_deposit(out)["models"] == 27
    assert main(["verify", str(out)]) == 0 and "3 intact shards of 27 models" in capsys.readouterr().out
    # a loose copy that differs from the bag's is named
    (out / "cohort.zarr.refs.json").write_text("{}")
    with pytest.raises(ReleaseError, match=r"cohort.zarr.refs.json: differs from data/cohort.zarr.refs.json"):
        verify_deposit(out)
    assert make_deposit(pristine, out)[1].read_bytes() == (pristine / "data" / "cohort.zarr.refs.json").read_bytes()
