"""The vendored labeled reference spine: one surface, per-vertex labels, landmark and ligament-site sets.

File ``spinecohort/data/reference/reference_spine.npz`` (rebuilt by ``scripts/build_reference.py``; its
README gives sources, licences and processing):

``vertices`` (N, 3) float32 mm RAS; ``faces`` (F, 3) int32; ``region``, ``level``, ``side`` (N,) int8
(:mod:`spinecohort.anatomy.labels`); ``landmarks_json``: the cohort :class:`Landmarks` of the reference;
``sets_json``: further vertex sets (ligament sites, facet articular surfaces, full concave endplates);
``build_json``: the build log (parameters, checks, counts).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from spinecohort.anatomy.labels import REGIONS
from spinecohort.cohort.landmarks import Landmarks


@dataclass(frozen=True)
class Reference:
    vertices: np.ndarray
    faces: np.ndarray
    region: np.ndarray
    level: np.ndarray
    side: np.ndarray
    landmarks: Landmarks
    sets: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    build: dict = field(default_factory=dict)

    def vertebra(self, level_index: int) -> np.ndarray:
        """Vertex indices of one vertebra (0 = T1 ... 16 = L5)."""
        return np.flatnonzero(self.level == level_index)

    def region_of(self, name: str) -> np.ndarray:
        return np.flatnonzero(self.region == REGIONS.index(name))


def default_path() -> Path:
    return Path(str(resources.files("spinecohort") / "data" / "reference" / "reference_spine.npz"))


def save_reference(ref: Reference, path: str | Path) -> None:
    sets = {k: {kk: np.asarray(vv).astype(int).tolist() for kk, vv in v.items()} for k, v in ref.sets.items()}
    np.savez_compressed(
        path,
        vertices=ref.vertices.astype(np.float32),
        faces=ref.faces.astype(np.int32),
        region=ref.region.astype(np.int8),
        level=ref.level.astype(np.int8),
        side=ref.side.astype(np.int8),
        landmarks_json=json.dumps(ref.landmarks.to_dict()),
        sets_json=json.dumps(sets),
        build_json=json.dumps(ref.build),
    )


def load_reference(path: str | Path | None = None) -> Reference:
    """The labeled reference (the vendored file by default); a clear error for a missing or foreign file."""
    path = Path(path) if path is not None else default_path()
    try:
        with np.load(path, allow_pickle=False) as z:
            sets = {
                k: {kk: np.asarray(vv, dtype=np.int64) for kk, vv in v.items()}
                for k, v in json.loads(str(z["sets_json"])).items()
            }
            # the endplate landmarks are rim bands (the clinical endplate line); the hex template is placed and
            # morphed on the whole endplate surface, which the landmarks carry beside them
            landmarks = replace(
                Landmarks.from_dict(json.loads(str(z["landmarks_json"]))),
                endplate_full_sup=sets.get("endplate_full_sup", {}),
                endplate_full_inf=sets.get("endplate_full_inf", {}),
            )
            return Reference(
                vertices=z["vertices"].astype(np.float64),
                faces=z["faces"].astype(np.int64),
                region=z["region"],
                level=z["level"],
                side=z["side"],
                landmarks=landmarks,
                sets=sets,
                build=json.loads(str(z["build_json"])),
            )
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a reference spine file ({type(exc).__name__}: {exc})") from exc
