"""Per-segment ligament laws of the lumbar segments from the model built on the same bones: Remus et al. 2021's
calibrated force-elongation curves (vendored: ``spinecohort/data/ligaments/remus2021_lumbar.csv``, its README
has the source, licence and the script that rebuilds it).  Units: N, mm.

Upstream each ligament of a segment is ``springs`` equal springs of mean length ``mean_length_mm`` (L); one
spring's rest length is L (1 + reference strain) and its force at strain s from that rest length is a quadratic
toe, k s^2 / (2 e_t), up to the transition strain e_t, then linear, k (s - e_t / 2) (`toe_linear_n`).  A negative
reference strain is a ligament taut in the neutral posture (pre-strained), a positive one a slack ligament.

Carried over as the ligament's whole force-elongation curve (`segment_force_n`): the force of all its springs
at an elongation d (mm) from the neutral posture, less the force they hold there.  A model's ligament of the
group in that segment, made of m fibres, gives each fibre 1/m of that force at the fibre's own elongation
(`curve_table`).  So the curve keeps its laxity and stiffness in millimetres and newtons whatever the fibre
count and lengths of the model's bundles (the upstream capsule springs are 1.9-2.6 mm, ours 1.5-7 mm).  Why
the force held in the neutral posture is subtracted: upstream it is balanced by the disc in the neutral posture
(a prestressed state our decks start without), so only the change from it acts; a pre-strained ligament
therefore also unloads (pushes) when it shortens, until it is slack.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np
import pandas as pd

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.mesh.template import LIGAMENT_GROUPS, HexTemplate

#: the vendored table's name in ``spinecohort/data/ligaments``, by the config's ``fe.lumbar_ligaments``
SOURCES = {"remus2021": "remus2021_lumbar.csv"}


@dataclass(frozen=True)
class SegmentLigament:
    """One ligament of one segment as upstream: ``springs`` springs of mean length ``mean_length_mm``, each with
    the reference strain, transition strain and linear stiffness (N per unit strain) of `toe_linear_n`."""

    springs: int
    mean_length_mm: float
    reference_strain: float
    transition_strain: float
    stiffness_n_per_spring: float


def load_segment_ligaments(source: str = "remus2021") -> dict[tuple[str, str], SegmentLigament]:
    """(segment e.g. ``"L5-S1"``, group) -> its `SegmentLigament`, from a vendored source (`SOURCES`)."""
    if source not in SOURCES:
        raise ValueError(f"fe.lumbar_ligaments: unknown source {source!r}; one of {sorted(SOURCES)} or null")
    path = resources.files("spinecohort") / "data" / "ligaments" / SOURCES[source]
    df = pd.read_csv(str(path))
    bad = sorted(set(df["group"]) - set(LIGAMENT_GROUPS))
    if bad:
        raise ValueError(f"{path}: ligament groups {bad} are not among {LIGAMENT_GROUPS}")
    return {
        (r.segment, r.group): SegmentLigament(
            int(r.springs),
            float(r.mean_length_mm),
            float(r.reference_strain),
            float(r.transition_strain),
            float(r.stiffness_n_per_spring),
        )
        for r in df.itertuples()
    }


def toe_linear_n(strain: np.ndarray, transition_strain: float, stiffness_n: float) -> np.ndarray:
    """Force (N) of one upstream spring at ``strain`` from its rest length: 0 when slack, k s^2 / (2 e_t) in the
    toe, k (s - e_t / 2) beyond (continuous in force and slope at e_t)."""
    s = np.asarray(strain, dtype=np.float64)
    et, k = transition_strain, stiffness_n
    return np.where(s <= 0, 0.0, np.where(s < et, k * s**2 / (2 * et), k * (s - et / 2)))


def segment_force_n(lig: SegmentLigament, elongation_mm: np.ndarray) -> np.ndarray:
    """Force (N) of the whole ligament (all its springs) at ``elongation_mm`` from the neutral posture, less the
    force it holds there (see the module docstring): 0 at 0, negative once it unloads, rising as it stretches."""
    rest = lig.mean_length_mm * (1 + lig.reference_strain)
    s = (lig.mean_length_mm + np.asarray(elongation_mm, dtype=np.float64)) / rest - 1
    neutral = 1 / (1 + lig.reference_strain) - 1  # the springs' strain in the neutral posture
    f = toe_linear_n(s, lig.transition_strain, lig.stiffness_n_per_spring)
    return lig.springs * (f - toe_linear_n(neutral, lig.transition_strain, lig.stiffness_n_per_spring))


def curve_table(
    lig: SegmentLigament, fibres: int, rest_length_mm: float, max_strain: float = 2.0, toe_points: int = 9
) -> tuple[tuple[float, float], ...]:
    """(force N, elongation mm) rows, ascending, of one of ``fibres`` equal fibres of the model's ligament (rest
    length ``rest_length_mm``): 1/fibres of `segment_force_n` at the fibre's elongation.  Rows: the fully unloaded
    force at -rest length, the slack point, ``toe_points`` across the toe, the transition, and ``max_strain``
    x the rest length (ccx holds the end forces beyond the table)."""
    if fibres < 1 or not rest_length_mm > 0:
        raise ValueError(f"a ligament curve needs >= 1 fibre and a rest length > 0 mm, got {fibres}, {rest_length_mm}")
    rest = lig.mean_length_mm * (1 + lig.reference_strain)
    slack = rest - lig.mean_length_mm  # elongation (mm) at which the upstream springs start to pull
    toe = slack + rest * np.linspace(0.0, lig.transition_strain, toe_points)
    d = np.unique(np.concatenate([[-rest_length_mm, min(slack, 0.0), 0.0], toe, [max_strain * rest_length_mm]]))
    d = d[(d >= -rest_length_mm) & (d <= max_strain * rest_length_mm)]
    force = segment_force_n(lig, d) / fibres
    return tuple((float(f) + 0.0, float(x)) for f, x in zip(force, d))


def node_bones(template: HexTemplate) -> np.ndarray:
    """(N,) index into ``LEVELS + ("S1",)`` of the bone every template node belongs to (the S1 plate and the
    sacrum: S1), -1 for a node of no bone (a disc's)."""
    from spinecohort.fe.connections import arch_owner

    bones = {lv: i for i, lv in enumerate([*LEVELS, "S1"])}
    layer_bone = np.array(
        [bones["S1"] if ly.get("kind") == "s1" else bones.get(ly.get("level"), -1) if ly.get("kind") == "body" else -1
         for ly in template.layers]
    )  # fmt: skip
    out = np.full(template.n_nodes, -1, dtype=np.int64)
    out[: template.n_hex_nodes] = layer_bone[template.layer_of_node]
    skin = arch_owner(template)
    out[np.fromiter(skin, dtype=np.int64, count=len(skin))] = [bones[v] for v in skin.values()]
    return out


def ligament_segments(template: HexTemplate) -> np.ndarray:
    """(L,) the segment (``"L5-S1"``) of every ligament element of the template, from its two end nodes' bones."""
    names = np.array([*LEVELS, "S1"])
    ends = np.sort(node_bones(template)[template.ligaments], axis=1)
    bad = (ends[:, 0] < 0) | (ends[:, 0] == ends[:, 1])
    if bad.any():
        a, b = template.ligaments[np.flatnonzero(bad)[0]]
        raise ValueError(f"ligament ({a}, {b}) does not join two bones: its ends belong to {names[ends[bad][0]]}")
    return np.char.add(np.char.add(names[ends[:, 0]], "-"), names[ends[:, 1]])
