"""Rib heads of the in-vitro thoracic specimens (costovertebral joints) as springs: switchable, ROM only.

Wilke et al. 2017's thoracic functional units kept their costovertebral joints: rib ``n``'s head sits on the
disc between T(n-1) and T(n), tied by the radiate ligament to both bodies and, by the costotransverse
ligaments, to the transverse process of T(n).  Ribs 2..10 bridge a disc; rib 1 and ribs 11, 12 articulate with
one vertebra only and bridge none (Gray's Anatomy), so the segments with a rib head are T1-T2 .. T9-T10.

Per bridged segment and side, one new node (the rib head) sits `offset_mm` outside the posterolateral rim of the disc,
at mid-height, and hangs on three linear spring groups, each of total stiffness `stiffness_n_per_mm`: to `rim_nodes`
outer-rim nodes of the upper vertebra's inferior endplate, to as many of the lower vertebra's superior endplate, and
to the lower vertebra's transverse-process tip.  No joint-level stiffness was obtained: the one published number, ~20
N/mm (J Biomech 2024;163:111923, two donors), was measured on the whole rib and cuts the T2-T3 unit's axial rotation
by 1 %, against 10-16 % measured in vitro (Liebsch & Wilke 2020); 200 N/mm, the default, reproduces the 10 %
(docs/explanation/fe-model.md "Calibration values and their sources").  A spine model without a rib cage (every
exported deck) has no rib heads: the heads are a feature of the specimens, which is why they live here, in the ROM
only (``rom.rib_heads.enabled``). Units: mm, N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.fe.connections import body_layer
from spinecohort.fe.facets import vertebra_frame
from spinecohort.mesh.template import HexTemplate

#: the segments whose disc a rib head bridges: (upper, lower) = (T(n-1), T(n)) for ribs n = 2..10
RIB_SEGMENTS: tuple[tuple[str, str], ...] = tuple((f"T{n - 1}", f"T{n}") for n in range(2, 11))
#: direction of the rib head from the disc centre in the segment's (lateral, anterior) plane, per side
#: (right = +lateral): posterolateral, where the demifacets sit on the bodies' sides
POSTEROLATERAL = np.array([0.6, -0.8])


@dataclass(frozen=True)
class RibHeads:
    """Rib-head springs (see the module docstring); stiffness per spring group (N/mm), offset (mm)."""

    stiffness_n_per_mm: float = 200.0
    offset_mm: float = 5.0
    rim_nodes: int = 3

    @classmethod
    def from_config(cls, cfg: dict | None) -> RibHeads | None:
        """``rom.rib_heads`` block -> RibHeads, or None when absent or disabled."""
        if not cfg or not cfg.get("enabled", False):
            return None
        return cls(
            stiffness_n_per_mm=float(cfg["stiffness_n_per_mm"]),
            offset_mm=float(cfg["offset_mm"]),
            rim_nodes=int(cfg["rim_nodes"]),
        )


@dataclass
class RibNodes:
    """The rib heads of a model: ``points`` (H, 3) mm of the new nodes; ``springs`` (S, 2) pairs of (new-node
    index, template node id); ``spring_groups`` (S,) name of each spring's group (``RIB_<up><lo>_<side>``);
    ``stiffness`` (S,) N/mm of each spring; ``tp_tips`` the template ids of the transverse-process tips used."""

    points: np.ndarray
    springs: np.ndarray
    spring_groups: np.ndarray
    stiffness: np.ndarray
    tp_tips: dict[str, np.ndarray]


def _tp_tip(
    template: HexTemplate,
    points: np.ndarray,
    upper: str,
    lower: str,
    lateral: np.ndarray,
    centre: np.ndarray,
    side: float,
) -> int:
    """Template id of the lower vertebra's transverse-process tip on `side` (+1 right, -1 left): the lower end
    of the segment's intertransverse ligament on that side."""
    up, lo = LEVELS.index(upper), LEVELS.index(lower)
    itl = template.ligaments[template.elsets["LIG_ITL"]]
    # the template has two ITLs per segment, left and right, in segment order (mesh.template.build_template)
    lower_ends = itl[2 * up : 2 * up + 2, 1]
    if lo != up + 1:
        raise ValueError(f"{upper}-{lower} is not a segment")
    x = (points[lower_ends] - centre) @ lateral
    return int(lower_ends[np.argmax(side * x)])


def rib_head_nodes(
    template: HexTemplate, points: np.ndarray, segments: list[tuple[str, str]], ribs: RibHeads
) -> RibNodes:
    """The rib heads of the given (upper, lower) segments that a rib bridges (`RIB_SEGMENTS`)."""
    g = template.grid
    n2 = len(g.nodes)
    unit = g.nodes[g.outer]
    unit = unit / np.linalg.norm(unit, axis=1, keepdims=True)
    pts, springs, groups, k = [], [], [], []
    tips: dict[str, list[int]] = {}
    for upper, lower in segments:
        if (upper, lower) not in RIB_SEGMENTS:
            continue
        frame, _ = vertebra_frame(template, points, lower)
        inf_up = body_layer(template, upper, 0.0) * n2
        sup_lo = body_layer(template, lower, 1.0) * n2
        for side, name in ((1.0, "R"), (-1.0, "L")):
            want = POSTEROLATERAL * np.array([side, 1.0])
            rim = np.argsort(-(unit @ want))[: ribs.rim_nodes]
            up_nodes, lo_nodes = inf_up + g.outer[rim], sup_lo + g.outer[rim]
            rim_pts = points[np.concatenate([up_nodes, lo_nodes])]
            outward = frame[:, :2] @ want
            outward /= np.linalg.norm(outward)
            head = rim_pts.mean(0) + ribs.offset_mm * outward
            tip = _tp_tip(template, points, upper, lower, frame[:, 0], rim_pts.mean(0), side)
            h = len(pts)
            pts.append(head)
            group = f"RIB_{upper}{lower}_{name}"
            for targets in (up_nodes, lo_nodes, np.array([tip])):
                for t in targets:
                    springs.append((h, int(t)))
                    groups.append(group)
                    k.append(ribs.stiffness_n_per_mm / len(targets))
            tips.setdefault(lower, []).append(tip)
    return RibNodes(
        points=np.asarray(pts, dtype=np.float64).reshape(-1, 3),
        springs=np.asarray(springs, dtype=np.int64).reshape(-1, 2),
        spring_groups=np.asarray(groups, dtype=object),
        stiffness=np.asarray(k, dtype=np.float64),
        tp_tips={v: np.asarray(t, dtype=np.int64) for v, t in tips.items()},
    )
