"""Correspondence by registration: the labeled reference moved onto each patient, bone by bone.

A :class:`LabeledReference` is any bone surface with a bone label per vertex and the landmark sets the
measurement and the FE stage read (``Landmarks``): :func:`synthetic_reference` builds one from the
generator's template; a reference from real anatomy plugs in through the same class.

Per patient (:func:`register_patient`): the reference is placed on the patient bone by bone, rigidly
(:func:`place_reference`: the pelvic ring first, then each vertebra from the one below - vertebrae move
relative to each other between patients far more than they deform).  Each patient
piece (a file or a connected component) is then assigned to the reference bone most of its points lie
nearest to - a file named L5 that lies where L4 belongs is an error.  Finally each bone is registered on
its own (ICP with scale, then layered BCPD) and the registered reference bones, in the reference's vertex order,
are the patient's corresponded surface.  Lengths in mm.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from spinecohort.cohort.bones import BONES, BoneInputError, BoneMesh, merge_bones
from spinecohort.cohort.landmarks import LEVELS, Landmarks
from spinecohort.mesh import registration as reg

log = logging.getLogger(__name__)

#: defaults of the config section ``register`` (docs/explanation/registration.md gives the measurements)
DEFAULTS = {
    "bone": {
        "lam": 8.0,
        "beta": 2.0,
        "gamma": 1.0,
        "K": 70,
        "w": 0.1,
        "max_iter": 100,
        "tol": 1.0e-5,
        "downsample_radius_mm": 1.5,
        "layers": 3,
        "sigma_start_mm": 10.0,
    },
    "bound_mean_mm": 0.5,
    "min_assigned_fraction": 0.6,
}


@dataclass(frozen=True)
class LabeledReference:
    """A reference surface (mm) with a bone per vertex: ``bone[i]`` indexes ``BONES``; ``landmarks``
    are the vertex sets every registered patient inherits."""

    points: np.ndarray
    faces: np.ndarray
    bone: np.ndarray
    landmarks: Landmarks

    def vertices_of(self, name: str) -> np.ndarray:
        return np.flatnonzero(self.bone == BONES.index(name))

    def faces_of(self, name: str) -> np.ndarray:
        """Triangles of one bone, renumbered to ``vertices_of(name)``."""
        idx = self.vertices_of(name)
        remap = np.full(len(self.points), -1)
        remap[idx] = np.arange(len(idx))
        return remap[self.faces[np.all(self.bone[self.faces] == BONES.index(name), axis=1)]]

    def save(self, path) -> None:
        np.savez(
            path,
            points=self.points,
            faces=self.faces,
            bone=self.bone,
            landmarks_json=np.array(json.dumps(self.landmarks.to_dict())),
        )

    @classmethod
    def load(cls, path) -> LabeledReference:
        with np.load(path, allow_pickle=False) as z:
            lm = Landmarks.from_dict(json.loads(str(z["landmarks_json"])))
            return cls(z["points"], z["faces"], z["bone"], lm)


def bone_labels(points: np.ndarray, faces: np.ndarray, landmarks: Landmarks) -> np.ndarray:
    """Bone of every vertex from the generator's part names: ``body_L3`` and ``posterior_L3`` -> L3,
    ``sacrum``, ``pelvis`` -> hip_left/hip_right by the side of each component's centroid (RAS: the
    patient's left at -x of the sacrum), ``femoral_head_L`` -> femur_left."""
    from spinecohort.cohort.bones import connected_components

    names = landmarks.part_names
    bone = np.full(len(points), -1, dtype=np.int16)
    for k, name in enumerate(names):
        lv = name.split("_", 1)[-1]
        if name.startswith(("body_", "posterior_")):
            target = lv
        elif name == "sacrum":
            target = "sacrum"
        elif name.startswith("femoral_head_"):
            target = "femur_left" if name.endswith("L") else "femur_right"
        elif name == "pelvis":
            continue
        else:
            raise ValueError(f"reference part {name!r} belongs to no bone")
        bone[landmarks.part == k] = BONES.index(target)
    pelvis = landmarks.part == names.index("pelvis")
    comp = connected_components(len(points), faces)
    mid_x = points[bone == BONES.index("sacrum"), 0].mean()
    for c in np.unique(comp[pelvis]):
        sel = comp == c
        bone[sel] = BONES.index("hip_left" if points[sel, 0].mean() < mid_x else "hip_right")
    if np.any(bone < 0):
        raise ValueError(f"{int((bone < 0).sum())} reference vertices belong to no bone")
    return bone


def synthetic_reference(resolution: str = "coarse", seed: int = 0) -> LabeledReference:
    """The generator's template as a labeled reference: a patient with the cohort's mean parameters,
    no shape noise, placed at the origin without axial rotation."""
    from spinecohort.cohort import synthetic as syn

    drawn = syn.draw_patient(np.random.default_rng(seed), "reference")
    p = replace(
        drawn,
        scale=1.0,
        PI=58.0,
        PT=27.0,
        LL=38.0,
        cobb=0.0,
        disc_factor=np.full_like(drawn.disc_factor, 0.875),
        axial_rotation_deg=0.0,
        translation=np.zeros(3),
    )
    verts, faces, lm, _ = syn.build_patient_mesh(p, syn.RESOLUTIONS[resolution], noise_mm=0.0, rng=None)
    return LabeledReference(verts, faces, bone_labels(verts, faces, lm), lm)


def real_reference(path=None) -> LabeledReference:
    """The real-bone reference (`spinecohort.anatomy.reference`, numbered as the real cohort's models:
    `spinecohort.cohort.real.first_use_reference`) as a labeled reference: its bone per vertex from its labels
    (a vertebra's level; sacrum and S1 plate; ilium and pubis, patient left / right = hip_left / hip_right;
    femoral heads by side), its landmarks with the facet surfaces, ligament sites and pedicles a registered
    patient inherits."""
    from spinecohort.anatomy.labels import REGIONS
    from spinecohort.anatomy.reference import load_reference
    from spinecohort.cohort.real import first_use_reference

    ref = first_use_reference(load_reference(path))
    vertebra = ref.level >= 0
    bone = np.where(vertebra, ref.level, -1).astype(np.int16)  # BONES begins with LEVELS

    def regions(*names):
        return ~vertebra & np.isin(ref.region, [REGIONS.index(n) for n in names])

    bone[regions("sacrum", "s1_plate")] = BONES.index("sacrum")
    for side, sign in (("left", -1), ("right", 1)):
        bone[regions("ilium", "pubis") & (ref.side == sign)] = BONES.index(f"hip_{side}")
        bone[regions("femoral_head") & (ref.side == sign)] = BONES.index(f"femur_{side}")
    if np.any(bone < 0):
        raise ValueError(f"{int((bone < 0).sum())} real reference vertices belong to no bone")
    return LabeledReference(ref.vertices, ref.faces, bone, ref.landmarks)


# ----------------------------------------------------------------------------------------------------------
#: bones placed together first (the pelvic ring), then the vertebrae from L5 up, each from its lower neighbour
_BASE = ("sacrum", "hip_left", "hip_right", "femur_left", "femur_right")
_BELOW = dict(zip(LEVELS, (*LEVELS[1:], "sacrum")))


def place_reference(reference: LabeledReference, cloud: np.ndarray) -> np.ndarray:
    """The reference's points (N, 3) moved bone by bone onto a patient's point cloud (mm), rigidly.

    The pelvic ring (sacrum, hip bones, femurs) is aligned as one body (CPD, then ICP), then each of its
    bones alone (ICP); each vertebra starts from the pose of the one below (L5 from the sacrum) and is
    refined by ICP.  Posture differs between patients by a few degrees per level, so a vertebra starts
    within a few mm of its place - never a level off, as a whole-spine fit can be."""
    base = np.isin(reference.bone, [BONES.index(b) for b in _BASE])
    start = reg.rigid_register(reference.points, cloud, scale=False)
    # the cloud's points nearest the roughly placed pelvic ring are the ring's target
    near = np.unique(cKDTree(cloud).query(start.transformed[base])[1])
    ring = reg.rigid_register(reference.points[base], cloud[near], scale=False)
    placed = np.empty_like(reference.points)

    def chain(pose, fit):
        return lambda x: fit.apply(pose(x))

    poses = {}
    for name in (*_BASE, *reversed(LEVELS)):
        lower = ring.apply if name in _BASE else poses[_BELOW[name]]
        idx = reference.vertices_of(name)
        fit = reg.icp_rigid(lower(reference.points[idx]), cloud)
        poses[name] = chain(lower, fit)
        placed[idx] = fit.transformed
    return placed


def assign_pieces(pieces: list[BoneMesh], placed: np.ndarray, ref_bone: np.ndarray) -> list[tuple[str, float]]:
    """Bone each piece's points lie nearest to (on the placed reference) and the fraction that do."""
    tree = cKDTree(placed)
    out = []
    for piece in pieces:
        votes = np.bincount(ref_bone[tree.query(piece.points)[1]], minlength=len(BONES))
        best = int(np.argmax(votes))
        out.append((BONES[best], float(votes[best] / votes.sum())))
    return out


def _require_all(found: set[str], patient: str, how: str) -> None:
    missing = [b for b in BONES if b not in found]
    if missing:
        raise BoneInputError(
            f"patient {patient}: no {', '.join(missing)} found ({how} {'it' if len(missing) == 1 else 'them'}). "
            f"Every patient of a cohort needs the reference's bones ({BONES[0]}..{BONES[-1]}): the shape model "
            f"needs the same vertices on every patient; remove the patient or complete its segmentation."
        )


def register_patient(
    reference: LabeledReference,
    pieces: list[BoneMesh],
    patient: str,
    named: bool,
    params: dict | None = None,
) -> tuple[np.ndarray, pd.DataFrame]:
    """Corresponded points (N, 3) mm of one patient in the reference's vertex order, and the report:
    one row per bone with the surface distance both ways (mean / 95th percentile / max, mm), the
    iterations, the seconds and the warnings.

    ``pieces``: the patient's bone meshes (``named=True``: their ``name`` is the bone, checked against
    where they lie) or unnamed connected components of one mesh (``named=False``: assigned here).  A bone
    of the reference the patient lacks is a :class:`BoneInputError` naming patient and bone."""
    p = {**DEFAULTS, **(params or {})}
    bone_p = {**DEFAULTS["bone"], **p["bone"]}
    if named:
        _require_all({b.name for b in pieces}, patient, "no file names")
    everything = np.concatenate([b.points for b in pieces])
    t0 = time.process_time()
    placed = place_reference(reference, everything)
    t_place = time.process_time() - t0
    assigned = assign_pieces(pieces, placed, reference.bone)
    by_bone: dict[str, list[BoneMesh]] = {}
    for piece, (name, frac) in zip(pieces, assigned):
        if named and name != piece.name:
            raise BoneInputError(
                f"patient {patient}: {piece.source} is named {piece.name} but lies where the reference has "
                f"{name} ({100 * frac:.0f} % of its points nearest to {name}): a mislabeled level?"
            )
        if frac < p["min_assigned_fraction"]:
            piece.warnings.append(f"{piece.source} {piece.name}: only {100 * frac:.0f} % of it lies nearest to {name}")
        by_bone.setdefault(name, []).append(piece)
    _require_all(set(by_bone), patient, "no component lies at")
    out = np.empty_like(reference.points)
    rows = []
    for name in BONES:
        t1 = time.process_time()
        target = merge_bones(by_bone[name], name) if len(by_bone[name]) > 1 else by_bone[name][0]
        idx = reference.vertices_of(name)
        out[idx] = register_bone(placed[idx], target, bone_p)
        row = {"patient": patient, "bone": name, "n_reference": len(idx), "n_patient": len(target.points)}
        row |= distance_row(out[idx], reference.faces_of(name), target)
        rows.append(row | {"cpu_s": time.process_time() - t1, "warnings": "; ".join(target.warnings)})
    report = pd.DataFrame(rows)
    report.attrs["placement_cpu_s"] = t_place
    log.info(
        "patient %s: placement %.1f s, bones %.1f s, mean distance %.3f mm (worst %s %.3f mm)",
        patient,
        t_place,
        report["cpu_s"].sum(),
        report["mean_mm"].mean(),
        report.loc[report["mean_mm"].idxmax(), "bone"],
        report["mean_mm"].max(),
    )
    return out, report


def register_bone(source: np.ndarray, target: BoneMesh, params: dict) -> np.ndarray:
    """The placed reference bone ``source`` (mm) registered onto ``target``: ICP with scale, then
    ``params['layers']`` BCPD layers (``params`` as the config's ``register.bone``)."""
    # the bone is placed already (ICP on the whole patient); ICP with scale on its own points finishes
    # pose and size (BCPD's similarity step alone left a hip bone 3 % too large: 0.68 mm against 0.28).
    # A CPD here cost two thirds of the time for the same result.
    fit = reg.icp_rigid(source, target.points, scale=True)
    res = reg.multilayer_register(
        fit.transformed,
        target.points,
        bound=1e-9,  # every layer runs: the later ones refine the correspondence, not only the distance
        max_layers=params["layers"],
        lam=params["lam"],
        beta=params["beta"],
        gamma=params["gamma"],
        K=params["K"],
        w=params["w"],
        max_iter=params["max_iter"],
        tol=params["tol"],
        downsample_radius=params["downsample_radius_mm"],
        first_sigma=params["sigma_start_mm"],
    )
    return res.deformed


def distance_row(registered: np.ndarray, faces: np.ndarray, target: BoneMesh) -> dict:
    """Surface distance (mm) of the registered bone to the patient's and of the patient's points back to the
    registered surface: mean, 95th percentile, max each."""
    out = {}
    for prefix, d in (
        ("", reg.surface_distance(registered, target.points, target.faces)),
        ("back_", reg.surface_distance(target.points, registered, faces)),
    ):
        out |= {f"{prefix}mean_mm": float(np.mean(d)), f"{prefix}p95_mm": float(np.percentile(d, 95))}
        out[f"{prefix}max_mm"] = float(np.max(d))
    return out


def failures(report: pd.DataFrame, bound_mean_mm: float) -> list[str]:
    """One sentence per bone whose mean surface distance (either way) exceeds the bound."""
    worst = np.maximum(report["mean_mm"], report["back_mean_mm"])
    return [
        f"patient {r.patient}, bone {r.bone}: mean surface distance {d:.3f} mm > {bound_mean_mm:g} mm"
        for r, d in zip(report.itertuples(), worst)
        if d > bound_mean_mm
    ]


def read_patient(path: str, patient: str, layout: str, units: str, aliases: dict | None = None) -> list[BoneMesh]:
    """A patient's pieces: per_bone = its folder's files, named and checked (units per file: a file in
    metres among millimetres is an error naming it); per_patient = the connected components of its mesh."""
    from spinecohort.cohort.bones import UNIT_TO_MM, check_bone, read_bone_folder, read_mesh, split_components

    if layout == "per_bone":
        return [check_bone(b, patient, units) for b in read_bone_folder(path, patient, aliases)]
    points, faces = read_mesh(path)
    extent = float(np.max(np.ptp(points, axis=0))) * UNIT_TO_MM[units]
    if not 150.0 <= extent <= 3000.0:
        raise BoneInputError(
            f"patient {patient} ({path}): largest extent {extent:.4g} mm read as '{units}'; a thoracolumbar spine "
            f"with pelvis spans 150-3000 mm. Set cohort.units to the file's unit (mm, cm or m)."
        )
    return [
        BoneMesh(b.name, b.points * UNIT_TO_MM[units], b.faces, b.source, b.warnings)
        for b in split_components(points, faces, path)
    ]


def register_patient_files(
    reference: LabeledReference,
    path: str,
    patient: str,
    layout: str,
    units: str,
    params: dict,
    out_stl: str,
    out_report: str,
) -> pd.DataFrame:
    """Read, register and write one patient: ``out_stl`` in the reference's vertex order and triangles,
    ``out_report`` one row per bone.  A bone above ``params['bound_mean_mm']`` raises after the report
    is logged (the log outlives the failed job), naming patient, bone and distance."""
    from spinecohort.cohort.stl_io import write_stl

    pieces = read_patient(path, patient, layout, units, params.get("bone_names") or None)
    points, report = register_patient(reference, pieces, patient, named=layout == "per_bone", params=params)
    log.info("registration report of %s:\n%s", patient, report.drop(columns=["warnings"]).round(3).to_string())
    failed = failures(report, params.get("bound_mean_mm", DEFAULTS["bound_mean_mm"]))
    if failed:
        raise BoneInputError("registration failed:\n  " + "\n  ".join(failed))
    write_stl(out_stl, points, reference.faces, name=patient)
    report.to_csv(out_report, index=False, float_format="%.4f")
    return report
