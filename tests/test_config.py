from pathlib import Path

import pytest
import yaml

from spinecohort.config import ConfigError, cohort_files, validate_config

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def _config(path="config/config.yaml"):
    return yaml.safe_load((ROOT / path).read_text())


@pytest.mark.parametrize("path", ["config/config.yaml", ".test/config/config.yaml"])
def test_shipped_configs_are_valid(path):
    validate_config(_config(path), SCHEMA)


def test_test_config_has_the_same_keys_as_the_real_one():
    def keys(d, prefix=""):
        return {prefix + k for k in d} | {
            x for k, v in d.items() if isinstance(v, dict) for x in keys(v, prefix + k + ".")
        }

    assert keys(_config()) == keys(_config(".test/config/config.yaml"))


def test_every_schema_key_is_documented():
    def walk(node, where="config"):
        for key, sub in node.get("properties", {}).items():
            assert sub.get("description"), f"{where}.{key} has no description"
            walk(sub, f"{where}.{key}")

    walk(yaml.safe_load(SCHEMA.read_text()))


def test_unknown_key_is_named_with_the_allowed_ones():
    c = _config()
    c["ssm"]["scalling"] = True
    with pytest.raises(
        ConfigError,
        match=r"ssm: Additional properties are not allowed \('scalling' was unexpected\).*allowed keys: gpa_max_iter",
    ):
        validate_config(c, SCHEMA)


def test_out_of_range_and_wrong_enum_are_named():
    c = _config()
    c["synthetic"]["n_patients"] = 2
    c["cohort"]["units"] = "inch"
    with pytest.raises(ConfigError) as err:
        validate_config(c, SCHEMA)
    msg = str(err.value)
    assert "synthetic.n_patients: 2 is less than the minimum of 3" in msg
    assert "cohort.units: 'inch' is not one of ['mm', 'cm', 'm']" in msg


def test_missing_cohort_folder(tmp_path):
    c = _config()
    c["cohort"]["source"] = "folder"
    c["cohort"]["folder"] = str(tmp_path / "nowhere")
    with pytest.raises(ConfigError, match="cohort.folder: '.*nowhere' is not an existing directory"):
        validate_config(c, SCHEMA)
    (tmp_path / "empty").mkdir()
    c["cohort"]["folder"] = str(tmp_path / "empty")
    with pytest.raises(ConfigError, match="holds no patient"):
        validate_config(c, SCHEMA)


def test_cohort_files_for_both_sources(tmp_path):
    c = _config()
    f = cohort_files(c)
    assert f["stls"][0] == "results/synthetic_cohort/P01.stl" and len(f["stls"]) == 42
    assert f["sheet"] == "results/synthetic_cohort/patients.csv"
    c["cohort"].update(source="folder", folder=str(tmp_path), sheet="my.xlsx")
    for name in ("B.stl", "A.stl"):
        (tmp_path / name).write_bytes(b"")
    # no landmark file: the meshes are registered (one job per patient), the reference gives the landmarks
    f = cohort_files(c)
    assert f["stls"] == ["results/registered/A.stl", "results/registered/B.stl"] and f["sheet"] == "my.xlsx"
    assert f["landmarks"] == "results/registered/landmarks.json"
    assert f["inputs"] == {"A": str(tmp_path / "A.stl"), "B": str(tmp_path / "B.stl")}
    # with a landmark file the STLs are taken as corresponded
    (tmp_path / "landmarks.json").write_text("{}")
    f = cohort_files(c)
    assert [Path(p).name for p in f["stls"]] == ["A.stl", "B.stl"] and f["sheet"] == "my.xlsx"
    assert f["landmarks"] == str(tmp_path / "landmarks.json") and "inputs" not in f
