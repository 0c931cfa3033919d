"""Landmark vertex sets carried with a cohort (or a template) in correspondence.

Every patient of a cohort has the same vertex count and order, so one set of vertex indices names the same
anatomical place on every patient and on every model sampled from the SSM.  Measurement never searches the
geometry: it reads the vertices named here.

Frame convention (millimetres): x towards the patient's right, y anterior, z up (RAS).  The left femoral
head therefore lies at -x and the right one at +x.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

#: Vertebral levels of the model, cranial to caudal.
LEVELS: tuple[str, ...] = tuple([f"T{i}" for i in range(1, 13)] + [f"L{i}" for i in range(1, 6)])

#: Discs between consecutive levels, cranial to caudal: ("T1", "T2"), ..., ("L5", "S1").
DISCS: tuple[tuple[str, str], ...] = tuple(zip(LEVELS, LEVELS[1:] + ("S1",)))


def disc_name(upper: str, lower: str) -> str:
    """Name of the disc between two levels, e.g. ``"L4-L5"``, ``"L5-S1"``."""
    return f"{upper}-{lower}"


#: the level -> vertices sets the spinopelvic measurement reads (with ``pubic_symphysis``)
MEASURED_SETS = ("endplate_sup", "endplate_inf", "rim_sup", "rim_inf", "femoral_head")


@dataclass(frozen=True)
class Landmarks:
    """Vertex index sets of one model topology.

    part: (N,) int16 part label of every vertex; ``part_names[label]`` names it.
    endplate_sup / endplate_inf: level -> indices of the planar endplate patch of the vertebral body
        (``endplate_sup`` also has ``"S1"``, the sacral plate).  The patches are sampled centrally
        symmetrically, so their vertex mean is the endplate centre.
    rim_sup / rim_inf: level -> indices of the outer ring of the same patches (anterior/posterior disc
        heights, the S1 posterosuperior corner).
    femoral_head: ``"L"`` / ``"R"`` -> indices of the spherical femoral-head surface (neck excluded).
    body: level -> all vertices of the vertebral body (endplates and wall).
    pubic_symphysis: indices of a patch at the pubic symphysis (anterior orientation check).
    anchors: ligament attachment vertices, name -> (17,) one vertex per level T1..L5 (e.g. ``spinous_tip``,
        ``tp_tip_L``, ``iap_tip_R``); optional for user cohorts (ligaments need them).
    endplate_full_sup / endplate_full_inf: level -> indices of the whole endplate surface, when
        ``endplate_sup/inf`` are only its rim band (a real concave endplate, whose clinical plane is fitted on the
        ring apophysis): the hex template's endplate layers are morphed onto this surface, which covers the
        nucleus (`endplate_surface`).  Optional: empty, ``endplate_sup/inf`` are the whole planar patches.
    sites: ``"<set>/<level>"`` -> indices of an anatomical surface patch of that level: the facet articular
        surfaces ``facet_surface_<sup|inf>_<left|right>`` and the ligament insertion sites ``site_<LIG>_<where>``
        (`spinecohort.anatomy.labels.LIGAMENT_SITES`) of the labeled reference, and the sacrum's one-vertex
        anchors ``anchor_<name>/S1`` (the lower side of L5-S1, which ``anchors`` does not hold).  Optional (a cohort without them
        gets single-spring ligaments at ``anchors`` and facet struts at configured angles); the hex template reads
        them (`spinecohort.mesh.ligament_sites`).
    """

    part: np.ndarray
    part_names: tuple[str, ...]
    endplate_sup: dict[str, np.ndarray]
    endplate_inf: dict[str, np.ndarray]
    rim_sup: dict[str, np.ndarray]
    rim_inf: dict[str, np.ndarray]
    femoral_head: dict[str, np.ndarray]
    body: dict[str, np.ndarray]
    pubic_symphysis: np.ndarray
    meta: dict = field(default_factory=dict)
    anchors: dict[str, np.ndarray] = field(default_factory=dict)
    endplate_full_sup: dict[str, np.ndarray] = field(default_factory=dict)
    endplate_full_inf: dict[str, np.ndarray] = field(default_factory=dict)
    sites: dict[str, np.ndarray] = field(default_factory=dict)

    def site(self, name: str, level: str) -> np.ndarray | None:
        """Vertex indices of the site ``name`` (e.g. ``facet_surface_sup_left``, ``site_LF_inf_right``) of
        ``level``, or None when the cohort has no such site."""
        return self.sites.get(f"{name}/{level}")

    def endplate_surface(self, side: str, level: str) -> np.ndarray:
        """Vertex indices of the whole endplate of `level` (`side` 'sup' | 'inf'): ``endplate_full_<side>`` where
        given, else the endplate patch ``endplate_<side>``."""
        full = getattr(self, f"endplate_full_{side}")
        return full[level] if level in full else getattr(self, f"endplate_{side}")[level]

    @property
    def n_vertices(self) -> int:
        return int(self.part.shape[0])

    def validate(self, n_vertices: int, source: str = "landmarks") -> None:
        """Raise ValueError naming ``source`` if any set is empty or indexes outside ``n_vertices``."""
        if self.n_vertices != n_vertices:
            raise ValueError(f"{source}: part labels cover {self.n_vertices} vertices but the meshes have {n_vertices}")
        for name, sets in self._sets().items():
            for key, idx in sets.items():
                if idx.size == 0:
                    raise ValueError(f"{source}: landmark set {name}[{key}] is empty")
                if idx.min() < 0 or idx.max() >= n_vertices:
                    raise ValueError(
                        f"{source}: landmark set {name}[{key}] indexes vertex {int(idx.max())} "
                        f"but the meshes have {n_vertices} vertices"
                    )
        missing = [lv for lv in LEVELS if lv not in self.endplate_sup or lv not in self.endplate_inf]
        if missing or "S1" not in self.endplate_sup:
            raise ValueError(f"{source}: endplate sets missing for {missing or ['S1']}")
        if set(self.femoral_head) != {"L", "R"}:
            raise ValueError(f"{source}: femoral_head must have exactly the keys 'L' and 'R'")

    def measured(self, extra=()) -> tuple[np.ndarray, Landmarks]:
        """The vertices the spinopelvic measurement reads (endplates, rims, femoral heads, symphysis) and the
        vertices ``extra``, sorted, and these landmarks on that row list: ``measure(points[:, rows],
        restricted)`` gives what ``measure(points, self)`` gives, bit for bit (every set keeps its order).
        ``body``, ``anchors`` and ``sites`` are dropped: the measurement does not read them."""
        sets = [np.ravel(v) for name in MEASURED_SETS for v in getattr(self, name).values()]
        rows = np.unique(np.concatenate([*sets, self.pubic_symphysis, np.asarray(extra, dtype=np.int64)]))
        restricted = replace(
            self,
            part=self.part[rows],
            body={},
            anchors={},
            endplate_full_sup={},
            endplate_full_inf={},
            sites={},
            pubic_symphysis=np.searchsorted(rows, self.pubic_symphysis),
            **{name: {k: np.searchsorted(rows, v) for k, v in getattr(self, name).items()} for name in MEASURED_SETS},
        )
        return rows, restricted

    def renumbered(self, order: np.ndarray) -> Landmarks:
        """These landmarks on the vertices renumbered so that new vertex ``k`` is old vertex ``order[k]``: the
        part labels reordered and every index set mapped to the new numbers (sorted; ``anchors`` keep their
        one-vertex-per-level order)."""
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        sets = {
            name: {k: inv[v] if name == "anchors" else np.sort(inv[v]) for k, v in per.items()}
            for name, per in self._sets().items()
            if name != "pubic_symphysis"
        }
        return replace(self, part=self.part[order], pubic_symphysis=np.sort(inv[self.pubic_symphysis]), **sets)

    def _sets(self) -> dict[str, dict[str, np.ndarray]]:
        return {
            "endplate_sup": self.endplate_sup,
            "endplate_inf": self.endplate_inf,
            "rim_sup": self.rim_sup,
            "rim_inf": self.rim_inf,
            "femoral_head": self.femoral_head,
            "body": self.body,
            "pubic_symphysis": {"": self.pubic_symphysis},
            "anchors": self.anchors,
            "endplate_full_sup": self.endplate_full_sup,
            "endplate_full_inf": self.endplate_full_inf,
            "sites": self.sites,
        }

    def to_dict(self) -> dict:
        out = {
            "frame": "RAS: x right, y anterior, z up; millimetres",
            "levels": list(LEVELS),
            "part_names": list(self.part_names),
            "part": self.part.astype(int).tolist(),
            "meta": self.meta,
        }
        for name, sets in self._sets().items():
            if (name.startswith("endplate_full") or name == "sites") and not sets:
                continue  # optional (`endplate_surface`, `site`): a cohort without them serializes as before
            if name == "pubic_symphysis":
                out[name] = self.pubic_symphysis.astype(int).tolist()
            else:
                out[name] = {k: v.astype(int).tolist() for k, v in sets.items()}
        return out

    @classmethod
    def from_dict(cls, d: dict) -> Landmarks:
        def idx(v) -> np.ndarray:
            return np.asarray(v, dtype=np.int64)

        def sets(name: str) -> dict[str, np.ndarray]:
            return {k: idx(v) for k, v in d[name].items()}

        return cls(
            part=np.asarray(d["part"], dtype=np.int16),
            part_names=tuple(d["part_names"]),
            endplate_sup=sets("endplate_sup"),
            endplate_inf=sets("endplate_inf"),
            rim_sup=sets("rim_sup"),
            rim_inf=sets("rim_inf"),
            femoral_head=sets("femoral_head"),
            body=sets("body"),
            pubic_symphysis=idx(d["pubic_symphysis"]),
            meta=d.get("meta", {}),
            anchors={k: idx(v) for k, v in d.get("anchors", {}).items()},
            endplate_full_sup={k: idx(v) for k, v in d.get("endplate_full_sup", {}).items()},
            endplate_full_inf={k: idx(v) for k, v in d.get("endplate_full_inf", {}).items()},
            sites={k: idx(v) for k, v in d.get("sites", {}).items()},
        )

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict()))

    @classmethod
    def from_cohort(cls, path: str | Path) -> Landmarks:
        """The landmarks of a cohort .npz (``loading.save_cohort``) without reading its meshes: a shard job
        needs these index sets only, not the 42 patients' 82 MB of points."""
        with np.load(path, allow_pickle=False) as z:
            return cls.from_dict(json.loads(str(z["landmarks_json"])))

    @classmethod
    def load(cls, path: str | Path) -> Landmarks:
        try:
            d = json.loads(Path(path).read_text())
            return cls.from_dict(d)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: not a readable landmark file ({type(exc).__name__}: {exc})") from exc
