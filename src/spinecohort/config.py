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
        elif not patient_inputs(config):
            problems.append(
                f"cohort.folder: '{folder}' holds no patient (no mesh file, no sub-folder of per-bone meshes)"
            )
    if problems:
        raise ConfigError("invalid configuration:\n  " + "\n  ".join(problems))


def cohort_layout(config: dict) -> str:
    """How a user folder is laid out: ``cohort.layout``, or for ``auto``: ``corresponded`` when a landmark
    file is given or present, ``per_bone`` when it holds sub-folders, else ``per_patient``."""
    c = config["cohort"]
    layout = c.get("layout", "auto")
    if layout != "auto":
        return layout
    folder = Path(c["folder"])
    if c["landmarks"] or (folder / "landmarks.json").is_file():
        return "corresponded"
    return "per_bone" if any(p.is_dir() for p in folder.iterdir()) else "per_patient"


def patient_inputs(config: dict) -> dict[str, str]:
    """Patient ID -> its mesh file (per_patient, corresponded) or its folder of bone files (per_bone)."""
    from spinecohort.layout import MESH_SUFFIXES

    folder = Path(config["cohort"]["folder"])
    if cohort_layout(config) == "per_bone":
        return {p.name: str(p) for p in sorted(folder.iterdir()) if p.is_dir() and not p.name.startswith(".")}
    suffixes = (".stl",) if cohort_layout(config) == "corresponded" else MESH_SUFFIXES
    return {p.stem: str(p) for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() in suffixes}


def cohort_files(config: dict) -> dict:
    """STL paths, sheet and landmark file of the configured cohort (synthetic, corresponded user STLs, or
    the registered user meshes), and ``inputs`` (patient -> file or folder) when a folder is registered."""
    from spinecohort.layout import Layout

    c = config["cohort"]
    if c["source"] == "synthetic":
        folder = Path(config["results"]) / "synthetic_cohort"
        ids = [f"P{i:02d}" for i in range(1, config["synthetic"]["n_patients"] + 1)]
        stls = [str(folder / f"{pid}.stl") for pid in ids]
        return {"stls": stls, "sheet": str(folder / "patients.csv"), "landmarks": str(folder / "landmarks.json")}
    folder = Path(c["folder"])
    inputs = patient_inputs(config)
    sheet = c["sheet"] or str(folder / "patients.csv")
    if cohort_layout(config) == "corresponded":
        return {
            "stls": list(inputs.values()),
            "sheet": sheet,
            "landmarks": c["landmarks"] or str(folder / "landmarks.json"),
        }
    layout = Layout(config["results"])
    return {
        "stls": [layout.registered_stl(pid) for pid in inputs],
        "sheet": sheet,
        "landmarks": layout.reference_landmarks,
        "inputs": inputs,
    }
