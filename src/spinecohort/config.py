"""Configuration validation against the JSON schema, with messages that name the offending key."""

from __future__ import annotations

from pathlib import Path

import jsonschema
import yaml


class ConfigError(ValueError):
    """The configuration is invalid; the message names the key and the problem."""


def load_schema(path: str | Path) -> dict:
    return yaml.safe_load(Path(path).read_text())


def _describe(err: jsonschema.ValidationError) -> str:
    where = ".".join(str(p) for p in err.absolute_path) or "(top level)"
    if err.validator == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        return f"{where}: {err.message}; allowed keys: {', '.join(allowed)}"
    return f"{where}: {err.message}"


def validate_config(config: dict, schema_path: str | Path) -> None:
    """Raise ConfigError listing every schema violation (unknown keys, wrong types, out-of-range values)
    and the semantic problems a schema cannot express (a missing cohort folder)."""
    validator = jsonschema.Draft202012Validator(load_schema(schema_path))
    errors = sorted(validator.iter_errors(config), key=lambda e: list(e.absolute_path))
    problems = [_describe(e) for e in errors]
    if not problems and config["cohort"]["source"] == "folder":
        folder = Path(config["cohort"]["folder"])
        if not config["cohort"]["folder"]:
            problems.append("cohort.folder: required when cohort.source is 'folder'")
        elif not folder.is_dir():
            problems.append(f"cohort.folder: '{folder}' is not an existing directory")
        elif not any(folder.glob("*.stl")):
            problems.append(f"cohort.folder: '{folder}' contains no .stl file")
    if problems:
        raise ConfigError("invalid configuration:\n  " + "\n  ".join(problems))


def cohort_files(config: dict) -> dict:
    """STL paths, sheet and landmark file of the configured cohort (synthetic or user folder)."""
    c = config["cohort"]
    if c["source"] == "synthetic":
        folder = Path(config["results"]) / "synthetic_cohort"
        ids = [f"P{i:02d}" for i in range(1, config["synthetic"]["n_patients"] + 1)]
        stls = [folder / f"{pid}.stl" for pid in ids]
    else:
        folder = Path(c["folder"])
        stls = sorted(folder.glob("*.stl"))
    return {
        "stls": [str(p) for p in stls],
        "sheet": c["sheet"] or str(folder / "patients.csv"),
        "landmarks": c["landmarks"] or str(folder / "landmarks.json"),
    }
