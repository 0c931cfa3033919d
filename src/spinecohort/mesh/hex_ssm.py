"""The hexahedral SSM: ``hex = hex_mean + DF . b`` with the triangulated SSM's deformation fields
transferred onto the nodes of the morphed hex template.

Transfer methods (``method``):

* ``"nearest"`` — the seed's: every hex node takes the deformation vector of the closest vertex of the
  triangulated mean (after an ICP alignment of the two means).  Interior nodes and disc nodes near two
  endplates jump between vertices of different surfaces, which inverts elements for large weights.
* ``"smooth"`` — per vertebral body, a least-squares affine fit of each mode's deformation of that body's
  vertices plus an inverse-distance interpolation of the residual from the 8 nearest body vertices; the S1
  plate layer uses the sacrum's vertices the same way; disc nodes take the linear interpolation of their two
  endplate nodes' fields with the weights that placed them in the mean.  Inside a body, the component along
  the body's axis is likewise the linear interpolation of the two endplate layers' (as the ray morph placed
  the columns, :func:`spinecohort.mesh.radial.axial_map`), the in-plane one stays the wall's: the residuals of
  wall and endplate vertices differ by up to 5 mm at 3 SD, and taken node by node they push a layer through
  the next (the lowest L5 layers of ~560 of the default grid's 16,807 models).  Linear in b by construction.

Surface elements (posterior elements, sacrum, pelvis, femoral heads) are SSM vertices: their fields are the
triangulated SSM's own, exactly, in both methods.

Models are ``hex_mean + DF . b`` followed, where the linear model collapses a disc (extreme weights), by
the disc-contact distraction of :mod:`spinecohort.mesh.contact` (``HexSSM.contact``; applied by
``shards.sample_points`` and ``models.hex_points_checked``, not by ``HexSSM.sample``, which stays the
linear formula).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spinecohort.cohort.landmarks import DISCS, Landmarks
from spinecohort.mesh.contact import ContactMap, contact_map
from spinecohort.mesh.template import HexTemplate, disc_runs
from spinecohort.ssm.model import SSM


@dataclass
class HexSSM:
    mean: np.ndarray  # (n_nodes, 3) mm: the morphed template
    fields: np.ndarray  # (m, n_nodes, 3) mm per +1 SD
    eigenvalues: np.ndarray  # (m,) of the triangulated SSM, for reference
    method: str
    contact: ContactMap | None = None  # disc-contact distraction (None: the linear formula only)

    def sample(self, weights: np.ndarray) -> np.ndarray:
        """Node coordinates (B, n_nodes, 3) mm for weights (B, m') in SD units, m' <= m."""
        w = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        out = self.mean + np.tensordot(w, self.fields[: w.shape[1]], axes=(1, 0))
        return out if np.ndim(weights) == 2 else out[0]

    def save(self, path: str | Path, **extra) -> None:
        contact = self.contact.arrays() if self.contact is not None else {}
        np.savez(
            path,
            mean=self.mean,
            fields=self.fields,
            eigenvalues=self.eigenvalues,
            method=np.array(self.method),
            **contact,
            **extra,
        )

    @classmethod
    def load(cls, path: str | Path) -> HexSSM:
        with np.load(path) as z:
            return cls(z["mean"], z["fields"], z["eigenvalues"], str(z["method"]), ContactMap.from_arrays(z))


def _affine_plus_residual(src_pts: np.ndarray, src_fields: np.ndarray, query: np.ndarray, k: int = 8) -> np.ndarray:
    """Fields (m, q, 3) at query points from fields (m, n, 3) given at src_pts (n, 3): affine least-squares
    part plus inverse-distance interpolated residual."""
    m, n, _ = src_fields.shape
    xh = np.c_[src_pts, np.ones(n)]
    coef, *_ = np.linalg.lstsq(xh, src_fields.transpose(1, 0, 2).reshape(n, -1), rcond=None)  # (4, 3m)
    affine_src = (xh @ coef).reshape(n, m, 3).transpose(1, 0, 2)
    resid = src_fields - affine_src
    qh = np.c_[query, np.ones(len(query))]
    out = (qh @ coef).reshape(len(query), m, 3).transpose(1, 0, 2)
    from scipy.spatial import cKDTree  # here: the shard jobs load a hex SSM and never build one

    k = min(k, n)
    d, idx = cKDTree(src_pts).query(query, k=k)
    w = 1.0 / (d**2 + 1e-6)
    w /= w.sum(1, keepdims=True)
    return out + np.einsum("qk,mqkc->mqc", w, resid[:, idx])


def transfer_fields(
    template: HexTemplate,
    hex_mean: np.ndarray,
    tri_ssm: SSM,
    landmarks: Landmarks,
    n_modes: int,
    method: str = "smooth",
    min_disc_height_mm: float | None = None,
) -> HexSSM:
    """Build the hex SSM on the morphed template nodes ``hex_mean`` (n_nodes, 3).

    ``min_disc_height_mm``: attach the disc-contact map that keeps every disc at least this high (mm);
    None: the linear formula only."""
    df_tri = tri_ssm.deformation_fields(n_modes)  # (m, N, 3)
    n_hex = template.n_hex_nodes
    fields = np.zeros((n_modes, len(hex_mean), 3))
    fields[:, n_hex:] = df_tri[:, template.surface_vertex]
    hex_pts = hex_mean[:n_hex]
    if method == "nearest":
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(tri_ssm.mean).query(hex_pts)
        fields[:, :n_hex] = df_tri[:, nearest]
    elif method == "smooth":
        n2 = len(template.grid.nodes)
        layers = template.layers
        hf = np.zeros((n_modes, len(layers), n2, 3))
        for L, layer in enumerate(layers):
            if layer["kind"] == "disc":
                continue
            # the S1 plate layer lies on the sacral plate: its own vertices carry its motion
            verts = (
                landmarks.body[layer["level"]] if layer["kind"] == "body" else landmarks.endplate_surface("sup", "S1")
            )
            hf[:, L] = _affine_plus_residual(tri_ssm.mean[verts], df_tri[:, verts], hex_pts[L * n2 : (L + 1) * n2])
        _interpolate_body_axial_fields(hf, hex_pts.reshape(len(layers), n2, 3), layers)
        _interpolate_disc_fields(hf, hex_pts.reshape(len(layers), n2, 3), layers)
        fields[:, :n_hex] = hf.reshape(n_modes, -1, 3)
    else:
        raise ValueError(f"unknown transfer method '{method}' (nearest | smooth)")
    contact = None if min_disc_height_mm is None else contact_map(landmarks, template, hex_mean, min_disc_height_mm)
    return HexSSM(hex_mean.copy(), fields, tri_ssm.eigenvalues[:n_modes].copy(), method, contact)


def _interpolate_disc_fields(hf: np.ndarray, mean_layers: np.ndarray, layers: list[dict]) -> None:
    """Disc node fields = (1 - s) * lower endplate field + s * upper, with s the node's position in the mean."""
    for first, L in disc_runs(layers):
        lower, upper = mean_layers[first - 1], mean_layers[L]
        d = upper - lower
        for k in range(first, L):
            s = np.einsum("nc,nc->n", mean_layers[k] - lower, d) / np.einsum("nc,nc->n", d, d)
            hf[:, k] = (1 - s)[None, :, None] * hf[:, first - 1] + s[None, :, None] * hf[:, L]


def body_runs(layers: list[dict]):
    """(first, last) node-layer indices of every vertebral body's layers (its inferior and superior endplates)."""
    starts = [k for k, layer in enumerate(layers) if layer["kind"] == "body" and layer["t"] == 0.0]
    for first in starts:
        last = first
        while layers[last]["t"] != 1.0:
            last += 1
        yield first, last


def _interpolate_body_axial_fields(hf: np.ndarray, mean_layers: np.ndarray, layers: list[dict]) -> None:
    """Inside each body (layers strictly between its endplates), replace the field's component along the body's
    axis by the linear interpolation of the two endplate layers' fields, with each node's position along its
    column in the mean; the in-plane component (the wall's waist) is kept.  hf (m, layers, n2, 3) in place."""
    for first, last in body_runs(layers):
        lower, upper = mean_layers[first], mean_layers[last]
        d = upper - lower  # (n2, 3) each column's span in the mean
        axis = d.mean(0) / np.linalg.norm(d.mean(0))
        inner = slice(first + 1, last)
        s = np.einsum("lnc,nc->ln", mean_layers[inner] - lower, d) / np.einsum("nc,nc->n", d, d)
        column = (1 - s)[None, ..., None] * hf[:, first, None] + s[None, ..., None] * hf[:, last, None]
        hf[:, inner] += ((column - hf[:, inner]) @ axis)[..., None] * axis


def contact_offsets(hex_ssm: HexSSM, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Disc gaps (B, 17) mm and level offsets (B, 17, 3) mm of models ``weights`` (B, m), computed on the
    endplate nodes only.  Infinite gaps and zero offsets without a contact map."""
    w = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    if hex_ssm.contact is None:
        return np.full((len(w), len(DISCS)), np.inf), np.zeros((len(w), len(DISCS), 3))
    return hex_ssm.contact.level_offsets_of_weights(hex_ssm.mean, hex_ssm.fields, w)


#: models of the transfer report's sample (``report_sample``): ~2 ms per model check and variant
REPORT_SAMPLE_MODELS = 800


def report_sample(n_models: int, n_levels: int, target: int = REPORT_SAMPLE_MODELS) -> np.ndarray:
    """Model IDs of the transfer report: every k-th ID from 0, k the smallest stride >= n_models / target
    that is coprime with the number of levels, so that along every mode each level is drawn about equally
    often (a stride of 7 on the 7-level grid would fix mode n's weight at -3).  All IDs when n <= target.

    Default grid: k = 22, 764 of the 16,807 models."""
    k = max(1, -(-int(n_models) // int(target)))
    while np.gcd(k, int(n_levels)) != 1:
        k += 1
    return np.arange(0, int(n_models), k)


def inverted_over_grid(
    hex_ssm: HexSSM, hexes: np.ndarray, weights: np.ndarray, chunk: int = 500, contact: bool = False
) -> dict:
    """Inverted-element statistics of every model of a weight grid (numba fused sample + check).

    Returns the fraction of inverted elements over all models and elements, the fraction of models with at
    least one, their count and the lowest scaled Jacobian met.  ``contact=True``: of the models after the
    disc-contact distraction (``hex_ssm.contact``), and how many models it moved.
    """
    from spinecohort.mesh.quality.kernels import morph_scaled_jacobian_nb, scaled_jacobian_batch_nb

    bad = models_bad = distracted = 0
    worst = np.inf
    m = weights.shape[1]
    n = hexes.max() + 1
    mean = np.ascontiguousarray(hex_ssm.mean[:n])
    fields = np.ascontiguousarray(hex_ssm.fields[:m, :n])
    for i in range(0, len(weights), chunk):
        wb = np.ascontiguousarray(weights[i : i + chunk], dtype=np.float64)
        sj = morph_scaled_jacobian_nb(mean, fields, wb, np.ascontiguousarray(hexes))
        if contact and hex_ssm.contact is not None:
            _, off = contact_offsets(hex_ssm, wb)
            moved = np.flatnonzero(np.abs(off).max(axis=(1, 2)) > 0)
            distracted += len(moved)
            if len(moved):
                pts = (
                    mean + np.tensordot(wb[moved], fields, axes=(1, 0)) + hex_ssm.contact.hex_offsets(off[moved])[:, :n]
                )
                sj[moved] = scaled_jacobian_batch_nb(np.ascontiguousarray(pts), np.ascontiguousarray(hexes))
        inv = sj <= 0
        bad += int(inv.sum())
        models_bad += int(inv.any(1).sum())
        worst = min(worst, float(sj.min()))
    total = len(weights) * len(hexes)
    out = {
        "inverted_element_fraction": bad / total,
        "models_with_inverted": models_bad,
        "models_with_inverted_fraction": models_bad / len(weights),
        "min_scaled_jacobian": worst,
    }
    if contact:
        out["models_distracted"] = distracted
    return out
