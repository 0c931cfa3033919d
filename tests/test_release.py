"""The release bag (spinecohort.release, rule ``release``): a valid BagIt bag, verification that names what
is wrong, reproducible archives, extraction that cannot escape its folder, config names that cannot move
the release out of ``results``, and ``export`` from a release."""

import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
import yaml

from spinecohort.cli import main
from spinecohort.config import ConfigError, validate_config
from spinecohort.release import ReleaseError, payload_layout, release_dir, safe_extract, verify_release, write_archive

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
    # the test config: 27 models in 3 shards of 9; a shard (~1.7 MB) exceeds part_size_mb 0.5 -> 1 part each
    rep = verify_release(pristine)
    assert rep["parts"] == 3 and rep["models"] == 27
    assert (pristine / "bagit.txt").read_text().startswith("BagIt-Version: 1.0\n")
    data = pristine / "data"
    names = {p.relative_to(data).as_posix() for p in data.rglob("*") if p.is_file()}
    assert {
        "Mean_Model (Template).inp",
        "Descriptive_List.xlsx",
        "README.md",
        "cohort.zarr.parts.csv",
        "model_inputs/ssm.npz",
        "model_inputs/faces.npy",
        "figures/mode_variation.png",
    } <= names
    assert sorted(n for n in names if n.startswith("cohort.zarr.part0")) == [
        f"cohort.zarr.part00{k}.tar" for k in (1, 2, 3)
    ]
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
    part = bag / "data" / "cohort.zarr.part002.tar"
    _flip_byte(part, part.stat().st_size // 2)
    with pytest.raises(ReleaseError, match=r"data/cohort.zarr.part002.tar: sha256 checksum mismatch"):
        verify_release(bag)


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


def test_verify_names_a_truncated_archive(bag, tmp_path):
    part = bag / "data" / "cohort.zarr.part003.tar"
    full = part.read_bytes()
    part.write_bytes(full[: len(full) // 2])
    with pytest.raises(
        ReleaseError,
        match=rf"data/cohort.zarr.part003.tar: {len(full) // 2} bytes, but "
        rf"metadata/files.json records {len(full)} \(truncated",
    ):
        verify_release(bag)
    # the unpacking step on its own: a tar cut inside a member is refused by name, whatever the manifests say
    with pytest.raises(ReleaseError, match=r"part003.tar: not a complete tar archive"):
        safe_extract(part, tmp_path / "out")


def test_verify_says_when_the_disk_cannot_hold_the_unpacked_store(bag, tmp_path, monkeypatch):
    """Unpacking needs the parts' bytes free where it unpacks; with 1 kB free the message names the place, both
    sizes and the way out, before tar starts (a full disk used to surface as an OSError deep in tarfile)."""
    import spinecohort.release as release

    parts = sum(p.stat().st_size for p in (bag / "data").glob("cohort.zarr.part*.tar"))
    real = shutil.disk_usage
    monkeypatch.setattr(release.shutil, "disk_usage", lambda path: real(path)._replace(free=1000))
    with pytest.raises(
        ReleaseError, match=rf"{parts / 1e9:.2f} GB\) into {tmp_path}, which has 0.00 GB free.*--tmpdir"
    ):
        verify_release(bag, workdir=tmp_path)
    monkeypatch.setattr(release.shutil, "disk_usage", real)
    assert verify_release(bag, workdir=tmp_path)["files"] > 0  # enough space: it verifies


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
        "data/cohort.zarr.part001.tar",
        "data/cohort.zarr.part003.tar",
        "data/README.md",
        "data/cohort.zarr.parts.csv",
    ):
        assert (again / f).read_bytes() == (pristine / f).read_bytes(), f
    # tag files carry the build date only; same day -> the same bytes too
    if (again / "bag-info.txt").read_text() == (pristine / "bag-info.txt").read_text():
        assert (again / "tagmanifest-sha256.txt").read_bytes() == (pristine / "tagmanifest-sha256.txt").read_bytes()


def test_archives_do_not_depend_on_file_metadata(tmp_path):
    # same bytes, different mtimes and permissions -> identical archives (fixed mtime, mode, owner, order)
    for k, (mtime, mode) in enumerate([(1_600_000_000, 0o600), (1_700_000_000, 0o644)]):
        root = tmp_path / f"s{k}"
        (root / "c" / "0").mkdir(parents=True)
        for rel, content in (("zarr.json", b"{}"), ("c/0/0", bytes(range(256)) * 12)):
            (root / rel).write_bytes(content)
            os.chmod(root / rel, mode)
            os.utime(root / rel, (mtime, mtime))
        write_archive(tmp_path / f"a{k}.tar", root, ["c/0/0", "zarr.json"])
    assert (tmp_path / "a0.tar").read_bytes() == (tmp_path / "a1.tar").read_bytes()
    with tarfile.open(tmp_path / "a0.tar") as tar:
        m = tar.getmembers()
    assert [x.name for x in m] == ["cohort.zarr/c/0/0", "cohort.zarr/zarr.json"]
    assert {(x.mtime, x.mode, x.uid, x.gid, x.uname) for x in m} == {(946684800, 0o644, 0, 0, "")}


def _malicious(path: Path, member: tarfile.TarInfo, payload: bytes = b"x") -> Path:
    with tarfile.open(path, "w", format=tarfile.PAX_FORMAT) as tar:
        good = tarfile.TarInfo("cohort.zarr/zarr.json")
        good.size = 2
        tar.addfile(good, io.BytesIO(b"{}"))  # a harmless member first: nothing may be written at all
        if member.isfile():
            member.size = len(payload)
            tar.addfile(member, io.BytesIO(payload))
        else:
            tar.addfile(member)
    return path


@pytest.mark.parametrize(
    "name, kind, message",
    [
        ("../evil.txt", tarfile.REGTYPE, "outside the extraction directory"),
        ("cohort.zarr/../../evil.txt", tarfile.REGTYPE, "outside the extraction directory"),
        ("/tmp/spinecohort-evil.txt", tarfile.REGTYPE, "outside the extraction directory"),
        ("cohort.zarr/link", tarfile.SYMTYPE, "is a symlink"),
        ("cohort.zarr/hard", tarfile.LNKTYPE, "is a hard link"),
    ],
)
def test_archive_members_cannot_escape_the_extraction_directory(tmp_path, name, kind, message):
    m = tarfile.TarInfo(name)
    m.type = kind
    if kind in (tarfile.SYMTYPE, tarfile.LNKTYPE):
        m.linkname = "/etc/passwd"
    archive = _malicious(tmp_path / "bad.tar", m)
    dest = tmp_path / "out" / "deep"
    with pytest.raises(ReleaseError, match=message) as err:
        safe_extract(archive, dest)
    assert "bad.tar" in str(err.value) and repr(name) in str(err.value)
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
    assert text.split("*HEADING")[1].split("** pure moment")[0] == plain.split("*HEADING")[1]
    step = text.split("** pure moment")[1]
    assert "*RIGID BODY, NSET=RB_L1" in step and "*BOUNDARY\nFIXED, 1, 3" in step and "*STEP, NLGEOM" in step
    cload = [float(line.split(",")[2]) for line in step.split("*CLOAD\n")[1].split("*")[0].splitlines()]
    assert sum(c * c for c in cload) ** 0.5 == pytest.approx(2000.0, rel=1e-6)  # N.mm


def test_cli_verify_and_unpack(bag, tmp_path, capsys):
    from spinecohort.store.zarr_store import check_store

    assert main(["verify", str(bag)]) == 0
    assert "3 archive parts unpack to a complete store of 27 models" in capsys.readouterr().out
    assert main(["unpack", str(bag), "--to", str(tmp_path / "u")]) == 0
    assert check_store(tmp_path / "u" / "cohort.zarr") == []  # every shard's sha256 sidecar matches
    readme = bag / "data" / "README.md"
    readme.write_bytes(readme.read_bytes().replace(b"# ", b"#!", 1))  # same size: only sha256 can tell
    assert main(["verify", str(bag), "--no-unpack"]) == 2
    assert "data/README.md: sha256 checksum mismatch" in capsys.readouterr().err
