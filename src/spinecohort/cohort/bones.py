"""Bones of a user's cohort: names, files, connected components and the checks a segmentation export needs.

A user brings either one mesh per patient holding every bone (``<folder>/<ID>.stl``, any triangulation and
vertex order) or one folder per patient with one file per bone (``<folder>/<ID>/<name>.stl``).  Bone
names are the reference's (``T1`` .. ``L5``, ``sacrum``, ``hip_left``, ``hip_right``, ``femur_left``,
``femur_right``); file stems are mapped to them by :func:`bone_of_file`, which accepts the names
segmentation tools write (TotalSegmentator's ``vertebrae_L3``, ``sacrum``, ``hip_left``,
``femur_right``) plus any aliases configured in ``register.bone_names``.

Every check here names the patient, the bone or file and the problem; warnings are logged with the
same names and kept in the registration report.  Lengths in mm.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import sparse

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.cohort.loading import UNIT_TO_MM
from spinecohort.cohort.surfaces import edge_check, signed_volume
from spinecohort.layout import MESH_SUFFIXES

log = logging.getLogger(__name__)

#: every bone of the reference, cranial to caudal, then left before right
BONES: tuple[str, ...] = (*LEVELS, "sacrum", "hip_left", "hip_right", "femur_left", "femur_right")
#: largest extent of any one bone in mm: a vertebra ~30-90 mm, a hip bone ~250 mm, a full femur ~500 mm
BONE_EXTENT_MM = (8.0, 600.0)

_LEVEL = re.compile(r"^(?:vertebrae?[_\- ]?)?([TL])(\d{1,2})$", re.IGNORECASE)
_SIDES = {"left": "left", "l": "left", "right": "right", "r": "right"}


class BoneInputError(ValueError):
    """A patient's bones cannot be used; the message names the patient, the file or bone and the problem."""


@dataclass
class BoneMesh:
    """One bone of one patient as read: points (mm) and triangles, with where it came from."""

    name: str
    points: np.ndarray
    faces: np.ndarray
    source: str
    warnings: list[str] = field(default_factory=list)


def bone_of_file(stem: str, aliases: dict[str, str] | None = None) -> str | None:
    """The bone a file stem names, or None: ``vertebrae_L3``/``L3``/``l3`` -> ``L3``, ``hip_left`` ->
    ``hip_left``, ``femur_R`` -> ``femur_right``, ``sacrum``; ``aliases`` (stem -> bone) first."""
    if aliases and stem in aliases:
        return aliases[stem]
    s = stem.strip()
    m = _LEVEL.match(s)
    if m:
        name = f"{m.group(1).upper()}{int(m.group(2))}"
        return name if name in LEVELS else None
    low = s.lower().replace("-", "_").replace(" ", "_")
    if low in ("sacrum", "s1", "vertebrae_s1"):
        return "sacrum"
    for kind in ("hip", "femur"):
        side = low[len(kind) + 1 :]
        if low.startswith(kind + "_") and side in _SIDES:
            return f"{kind}_{_SIDES[side]}"
    return None


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points (V, 3) in file units and triangles (F, 3) of any surface mesh pyvista reads; polygons are
    triangulated and coincident points merged (STL stores each triangle's corners apart)."""
    import pyvista as pv

    path = Path(path)
    try:
        mesh = pv.read(str(path))
    except Exception as exc:  # readers raise many types for malformed files
        raise BoneInputError(f"{path}: cannot read the mesh ({type(exc).__name__}: {exc})") from exc
    surf = mesh.extract_surface(algorithm=None).triangulate().clean(tolerance=0.0)
    if surf.n_cells == 0:
        raise BoneInputError(f"{path}: the mesh has no triangles")
    faces = np.asarray(surf.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
    points = np.asarray(surf.points, dtype=float)
    if not np.all(np.isfinite(points)):
        raise BoneInputError(f"{path}: NaN or infinite coordinates")
    return points, faces


def connected_components(n_points: int, faces: np.ndarray) -> np.ndarray:
    """Component label (V,) of every point of a triangle mesh (points joined by shared triangles)."""
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_points, n_points))
    return sparse.csgraph.connected_components(graph, directed=False)[1]


def check_bone(bone: BoneMesh, patient: str, units: str) -> BoneMesh:
    """Units to mm, extent plausible for one bone (else an error naming the file: a file in metres among
    millimetres is caught here), and named warnings for open / non-manifold surfaces and inverted normals.

    Registration reads points only, so an open, non-manifold or inside-out surface still registers; the
    warnings say so in the report because the surface distance is then the thing to look at."""
    pts = bone.points * UNIT_TO_MM[units]
    extent = float(np.max(np.ptp(pts, axis=0)))
    lo, hi = BONE_EXTENT_MM
    if not lo <= extent <= hi:
        guess = ""
        for unit, factor in UNIT_TO_MM.items():
            if lo <= extent / UNIT_TO_MM[units] * factor <= hi and unit != units:
                guess = f"; read as '{unit}' it would be {extent / UNIT_TO_MM[units] * factor:.4g} mm"
                break
        raise BoneInputError(
            f"patient {patient}, bone {bone.name} ({bone.source}): largest extent {extent:.4g} mm read as "
            f"'{units}', outside the {lo:g}-{hi:g} mm of any one bone{guess}. Mixed units in one cohort are "
            f"not converted: export every file in cohort.units."
        )
    found = surface_warnings(pts, bone.faces, bone.source)
    for w in found:
        log.warning("patient %s, bone %s: %s", patient, bone.name, w)
    return BoneMesh(bone.name, pts, bone.faces, bone.source, bone.warnings + found)


def surface_warnings(points: np.ndarray, faces: np.ndarray, source: str) -> list[str]:
    """Named warnings for an open or non-manifold surface, inconsistent or inward triangle orientation."""
    closed, oriented = edge_check(faces)
    if not closed:
        return [f"open or non-manifold surface ({source})"]
    if not oriented:
        return [f"inconsistently oriented triangles ({source})"]
    if signed_volume(points, faces) < 0:
        return [f"inward normals: the surface is inside out ({source})"]
    return []


def read_bone_folder(folder: str | Path, patient: str, aliases: dict[str, str] | None = None) -> list[BoneMesh]:
    """One file per bone in ``folder``: named by :func:`bone_of_file`.  A file naming no bone, or two
    files naming the same bone, is an error naming both."""
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise BoneInputError(f"patient {patient}: {folder} holds no mesh file ({', '.join(MESH_SUFFIXES)})")
    seen: dict[str, Path] = {}
    out = []
    for path in files:
        name = bone_of_file(path.stem, aliases)
        if name is None:
            raise BoneInputError(
                f"patient {patient}: {path.name} names no bone (expected e.g. vertebrae_L3, L3, sacrum, hip_left, "
                f"femur_right; map other names in register.bone_names)"
            )
        if name in seen:
            raise BoneInputError(f"patient {patient}: {seen[name].name} and {path.name} both name bone {name}")
        seen[name] = path
        pts, faces = read_mesh(path)
        out.append(BoneMesh(name, pts, faces, str(path)))
    return out


def split_components(points: np.ndarray, faces: np.ndarray, source: str) -> list[BoneMesh]:
    """The connected components of one whole-patient mesh, unnamed yet (``name`` = ``component_<k>``),
    largest first; the caller assigns them to bones after aligning the reference."""
    label = connected_components(len(points), faces)
    used = np.unique(faces)
    counts = np.bincount(label[used], minlength=label.max() + 1)
    out = []
    for k in np.argsort(-counts):
        if counts[k] == 0:
            continue
        keep = np.flatnonzero(label == k)
        remap = np.full(len(points), -1)
        remap[keep] = np.arange(len(keep))
        tri = remap[faces[np.all(label[faces] == k, axis=1)]]
        name = f"component_{len(out)}"
        out.append(BoneMesh(name, points[keep], tri, source, surface_warnings(points[keep], tri, f"{source} {name}")))
    return out


def merge_bones(parts: list[BoneMesh], name: str) -> BoneMesh:
    """One bone from several meshes (the components a segmentation split one bone into)."""
    offsets = np.cumsum([0] + [len(p.points) for p in parts[:-1]])
    return BoneMesh(
        name,
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
        parts[0].source,
        [w for p in parts for w in p.warnings],
    )
