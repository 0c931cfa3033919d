"""A cohort written as a user brings it: every bone re-triangulated on its own, vertices shuffled.

``spinecohort write-cohort-folder`` writes the synthetic cohort (ground truth known) either as one mesh
per patient holding every bone (``<out>/<ID>.stl``) or as one folder per patient with one file per bone
named as TotalSegmentator names them (``<out>/<ID>/vertebrae_L3.stl``, ``sacrum.stl``, ``hip_left.stl``,
``femur_right.stl``), plus the patient sheet.  No landmark file: the registration gives the landmarks.
Lengths in mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.cohort.bones import BONES
from spinecohort.cohort.stl_io import write_stl


def export_name(bone: str) -> str:
    """The file stem a segmentation tool writes for a bone (TotalSegmentator's names)."""
    return f"vertebrae_{bone}" if bone[0] in "TL" and bone[1:].isdigit() else bone


def retriangulate(
    points: np.ndarray, faces: np.ndarray, rng: np.random.Generator, reduction: tuple[float, float] = (0.55, 0.8)
) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with a different tessellation: every triangle split in four (midpoints: the
    surface is unchanged), then quadric decimation removes a random ``reduction`` share of the triangles
    (new vertex positions on the surface), then points and triangles are shuffled.  Mesh in mm."""
    from spinecohort.mesh.vtk_mesh import surface

    fine = surface(points, faces).subdivide(1, subfilter="linear")
    coarse = fine.decimate(float(rng.uniform(*reduction)), volume_preservation=True)
    tri = np.asarray(coarse.faces).reshape(-1, 4)[:, 1:]
    pts = np.asarray(coarse.points, dtype=float)
    used = np.unique(tri)
    remap = np.full(len(pts), -1)
    perm = rng.permutation(len(used))
    remap[used] = perm
    out = np.empty((len(used), 3))
    out[perm] = pts[used]
    tri = remap[tri][rng.permutation(len(tri))]
    tri = np.roll(tri, int(rng.integers(3)), axis=1)  # a cyclic shift keeps each triangle's orientation
    return out, tri


def bone_meshes(points: np.ndarray, faces: np.ndarray, bone: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Split a corresponded patient into its bones: name -> (points, faces renumbered)."""
    out = {}
    for k, name in enumerate(BONES):
        idx = np.flatnonzero(bone == k)
        remap = np.full(len(points), -1)
        remap[idx] = np.arange(len(idx))
        out[name] = (points[idx], remap[faces[np.all(bone[faces] == k, axis=1)]])
    return out


def write_user_folder(
    out_dir: str | Path,
    ids: list[str],
    points: np.ndarray,
    faces: np.ndarray,
    bone: np.ndarray,
    table: pd.DataFrame,
    per_bone: bool,
    seed: int = 0,
) -> list[Path]:
    """Write every patient re-triangulated independently (bone by bone) and shuffled; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    written = []
    for pid, pts in zip(ids, points):
        pieces = {name: retriangulate(p, f, rng) for name, (p, f) in bone_meshes(pts, faces, bone).items()}
        if per_bone:
            (out / pid).mkdir(exist_ok=True)
            for name, (p, f) in pieces.items():
                written.append(out / pid / f"{export_name(name)}.stl")
                write_stl(written[-1], p, f, name=f"{pid} {name}")
            continue
        order = rng.permutation(len(pieces))
        names = [list(pieces)[k] for k in order]
        offsets = np.cumsum([0] + [len(pieces[n][0]) for n in names[:-1]])
        allp = np.concatenate([pieces[n][0] for n in names])
        allf = np.concatenate([pieces[n][1] + o for n, o in zip(names, offsets)])
        written.append(out / f"{pid}.stl")
        write_stl(written[-1], allp, allf, name=pid)
    table.to_csv(out / "patients.csv", index=False, float_format="%.6f")
    return written + [out / "patients.csv"]
