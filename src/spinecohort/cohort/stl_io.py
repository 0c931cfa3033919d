"""STL reading and writing with a deterministic, order-preserving vertex merge.

numpy-stl parses binary and ASCII STL into raw triangles.  STL stores no vertex indices, so the shared
vertices are recovered by merging equal coordinates; the merged vertices are numbered in order of first
occurrence in the file (not sorted, as meshio's reader does), which is what makes the vertex order of a
mesh survive a write/read round trip when its vertices were numbered by first use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from stl import mesh as stl_mesh
from stl.base import RemoveDuplicates
from stl.stl import Mode


class MeshInputError(ValueError):
    """A mesh file cannot be used; the message names the file and the problem."""


def _check_binary_size(path: Path, data: bytes) -> None:
    if len(data) < 84:
        raise MeshInputError(f"{path}: truncated STL ({len(data)} bytes, a binary STL header alone is 84)")
    n = int.from_bytes(data[80:84], "little")
    expected = 84 + 50 * n
    if len(data) != expected:
        raise MeshInputError(
            f"{path}: binary STL header announces {n} triangles ({expected} bytes) but the file has "
            f"{len(data)} bytes (truncated or corrupted)"
        )


def read_stl(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 in file units and faces (F, 3) int64 of an ASCII or binary STL."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MeshInputError(f"{path}: cannot read ({exc.strerror})") from exc
    if not data.strip():
        raise MeshInputError(f"{path}: empty file")
    is_ascii = data.lstrip()[:5].lower() == b"solid" and b"facet" in data[:4096]
    if not is_ascii:
        _check_binary_size(path, data)
    try:
        m = stl_mesh.Mesh.from_file(
            str(path),
            calculate_normals=False,
            remove_empty_areas=False,
            remove_duplicate_polygons=RemoveDuplicates.NONE,
            mode=Mode.ASCII if is_ascii else Mode.BINARY,
        )
    except Exception as exc:  # numpy-stl raises several types for malformed input
        raise MeshInputError(f"{path}: not a valid STL ({type(exc).__name__}: {exc})") from exc
    tri = np.asarray(m.vectors)
    if tri.shape[0] == 0:
        raise MeshInputError(f"{path}: the STL has no triangles")
    finite = np.isfinite(tri).all(axis=(1, 2))
    if not finite.all():
        raise MeshInputError(f"{path}: {int((~finite).sum())} triangles have NaN or infinite coordinates")
    return merge_vertices(tri)


def merge_vertices(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bitwise-equal corners of (F, 3, 3) triangles; vertices (float64) numbered by first occurrence.

    Corners are compared as raw bytes (one 1-D sort of fixed-size keys, 4x faster than a row-wise
    ``np.unique(axis=0)``); STL data is float32, so equal means equal in the file.
    """
    flat = np.ascontiguousarray(triangles.reshape(-1, 3))
    keys = flat.view(f"V{flat.dtype.itemsize * 3}").ravel()
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    rank = np.empty(len(uniq), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(uniq))
    vertices = flat[np.sort(first)].astype(np.float64)
    faces = rank[inverse.ravel()].reshape(-1, 3)
    return vertices, faces


def write_stl(
    path: str | Path, vertices: np.ndarray, faces: np.ndarray, ascii: bool = False, name: str = "spinecohort"
) -> None:
    """Write a triangle mesh as binary (default) or ASCII STL; coordinates are stored as float32.

    The binary header is fixed text (numpy-stl's own writer stamps the time into it), so the same mesh
    always gives the same bytes.
    """
    m = stl_mesh.Mesh(np.zeros(len(faces), dtype=stl_mesh.Mesh.dtype), name=name, calculate_normals=False)
    m.vectors[:] = np.asarray(vertices)[np.asarray(faces)]
    m.update_normals()
    if ascii:
        m.save(str(path), mode=Mode.ASCII)
        return
    header = f"binary STL {name} (spinecohort, mm)".encode("ascii", "replace")[:80].ljust(80, b" ")
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(np.uint32(len(faces)).tobytes())
        fh.write(m.data.tobytes())
