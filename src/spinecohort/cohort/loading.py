"""The patient cohort: a folder of STL files in vertex correspondence, a parameter sheet and a landmark file.

``results/synthetic_cohort/`` written by the generator has exactly the layout a user with real data
provides, so the synthetic and the user-supplied cohort go through the same loader and the same checks.
Every check raises :class:`CohortInputError` naming the file and the problem.
"""

from __future__ import annotations

import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.atomic import atomic_write
from spinecohort.cohort.landmarks import Landmarks
from spinecohort.cohort.stl_io import MeshInputError, read_stl, write_stl

log = logging.getLogger(__name__)

UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: A thoracolumbar spine with pelvis spans roughly 400-800 mm; anything far outside is a unit error.
PLAUSIBLE_EXTENT_MM = (150.0, 3000.0)


class CohortInputError(ValueError):
    """The cohort cannot be used; the message names the file and the problem."""


@dataclass
class Cohort:
    ids: list[str]
    points: np.ndarray  # (P, N, 3) mm
    faces: np.ndarray  # (F, 3)
    landmarks: Landmarks
    table: pd.DataFrame  # patient sheet, one row per ID in ``ids`` order


def write_cohort_folder(
    out_dir: str | Path,
    ids: list[str],
    points: np.ndarray,
    faces: np.ndarray,
    landmarks: Landmarks,
    table: pd.DataFrame,
) -> list[Path]:
    """Write ``<ID>.stl`` per patient, ``patients.csv`` and ``landmarks.json``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for pid, pts in zip(ids, points):
        written.append(out / f"{pid}.stl")
        write_stl(written[-1], pts, faces, name=pid)
    table.to_csv(out / "patients.csv", index=False, float_format="%.6f")
    landmarks.save(out / "landmarks.json")
    return written + [out / "patients.csv", out / "landmarks.json"]


def triangle_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Areas (F,) in mm^2."""
    a, b, c = (points[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def check_mesh(
    path: Path,
    points: np.ndarray,
    faces: np.ndarray,
    units: str,
    degenerate_area_mm2: float,
    max_degenerate_fraction: float,
) -> np.ndarray:
    """Validate one patient mesh; returns its points converted to mm."""
    if not np.all(np.isfinite(points)):
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise CohortInputError(f"{path}: {bad} vertices have NaN or infinite coordinates")
    pts = points * UNIT_TO_MM[units]
    extent = float(np.max(pts.max(0) - pts.min(0)))
    lo, hi = PLAUSIBLE_EXTENT_MM
    if extent < lo:
        guess = " (it looks like metres)" if extent < 3.0 else ""
        raise CohortInputError(
            f"{path}: largest extent is {extent:.4g} mm after reading as '{units}'{guess}; a thoracolumbar "
            f"spine spans {lo:.0f}-{hi:.0f} mm. Set cohort.units to the file's unit (mm, cm or m)."
        )
    if extent > hi:
        raise CohortInputError(
            f"{path}: largest extent is {extent:.4g} mm after reading as '{units}', larger than any spine "
            f"({hi:.0f} mm). Check cohort.units."
        )
    areas = triangle_areas(pts, faces)
    n_bad = int((areas < degenerate_area_mm2).sum())
    if n_bad > max_degenerate_fraction * len(faces):
        raise CohortInputError(
            f"{path}: {n_bad} of {len(faces)} triangles ({100 * n_bad / len(faces):.2f} %) are degenerate "
            f"(area < {degenerate_area_mm2:g} mm^2); at most {100 * max_degenerate_fraction:g} % allowed"
        )
    return pts


def read_patient_sheet(path: str | Path) -> pd.DataFrame:
    path = Path(path)
    try:
        if path.suffix.lower() in (".xlsx", ".xls"):
            table = pd.read_excel(path)
        else:
            table = pd.read_csv(path)
    except Exception as exc:
        raise CohortInputError(f"{path}: cannot read the patient sheet ({type(exc).__name__}: {exc})") from exc
    if "ID" not in table.columns:
        raise CohortInputError(f"{path}: the patient sheet has no 'ID' column (columns: {list(table.columns)})")
    table["ID"] = table["ID"].astype(str)
    dup = table["ID"][table["ID"].duplicated()].tolist()
    if dup:
        raise CohortInputError(f"{path}: duplicate patient IDs {dup}")
    return table


def load_cohort(
    stl_paths: list[str | Path],
    sheet_path: str | Path,
    landmarks_path: str | Path,
    units: str = "mm",
    degenerate_area_mm2: float = 1e-6,
    max_degenerate_fraction: float = 0.001,
) -> Cohort:
    """Read and validate a cohort; patients are ordered as ``stl_paths``, IDs are the file stems."""
    if units not in UNIT_TO_MM:
        raise CohortInputError(f"cohort.units must be one of {sorted(UNIT_TO_MM)}, got '{units}'")
    stl_paths = [Path(p) for p in stl_paths]
    if len(stl_paths) < 3:
        raise CohortInputError(f"an SSM needs at least 3 patients, got {len(stl_paths)} STL files")
    ids = [p.stem for p in stl_paths]
    table = read_patient_sheet(sheet_path)
    missing = sorted(set(ids) - set(table["ID"]))
    extra = sorted(set(table["ID"]) - set(ids))
    if missing or extra:
        raise CohortInputError(
            f"{sheet_path}: patient IDs do not match the STL files: "
            f"{'no row for ' + ', '.join(missing) if missing else ''}"
            f"{'; ' if missing and extra else ''}"
            f"{'no STL for ' + ', '.join(extra) if extra else ''}"
        )
    table = table.set_index("ID").loc[ids].reset_index()

    points, faces0, ref = [], None, None
    for path in stl_paths:
        try:
            pts, faces = read_stl(path)
        except MeshInputError as exc:
            raise CohortInputError(str(exc)) from exc
        if faces0 is None:
            faces0, ref = faces, path
        elif len(pts) != len(points[0]):
            raise CohortInputError(
                f"{path}: {len(pts)} vertices but {ref} has {len(points[0])}: the meshes are not in vertex "
                f"correspondence (every patient needs the same vertices in the same order)"
            )
        elif not np.array_equal(faces, faces0):
            n_diff = int(np.any(faces != faces0, axis=1).sum()) if faces.shape == faces0.shape else len(faces)
            raise CohortInputError(
                f"{path}: same vertex count as {ref} but {n_diff} triangles connect different vertices: "
                f"the meshes are not in vertex correspondence"
            )
        points.append(check_mesh(path, pts, faces, units, degenerate_area_mm2, max_degenerate_fraction))
    landmarks = Landmarks.load(landmarks_path)
    try:
        landmarks.validate(len(points[0]), source=str(landmarks_path))
    except ValueError as exc:
        raise CohortInputError(str(exc)) from exc
    log.info("cohort: %d patients, %d vertices, %d triangles", len(ids), len(points[0]), len(faces0))
    return Cohort(ids, np.stack(points), faces0, landmarks, table)


def save_cohort(path: str | Path, cohort: Cohort) -> None:
    """One .npz with the stacked points, faces, part labels, landmarks (JSON) and patient table (CSV)."""
    with atomic_write(path) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            ids=np.array(cohort.ids),
            points=cohort.points,
            faces=cohort.faces,
            part=cohort.landmarks.part,
            landmarks_json=np.array(json.dumps(cohort.landmarks.to_dict())),
            table_csv=np.array(cohort.table.to_csv(index=False)),
        )


def load_cohort_npz(path: str | Path) -> Cohort:
    with np.load(path, allow_pickle=False) as z:
        return Cohort(
            ids=[str(s) for s in z["ids"]],
            points=z["points"],
            faces=z["faces"],
            landmarks=Landmarks.from_cohort(path),
            table=pd.read_csv(io.StringIO(str(z["table_csv"])), dtype={"ID": str}),
        )
