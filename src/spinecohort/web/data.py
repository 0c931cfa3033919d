"""Data access of the cohort platform: one read-only view of a results folder or of a release bag.

Everything the page shows or offers for download comes through :class:`CohortData`, and every answer is
computed by the package's own functions: range queries by ``measure.tables.query_mask`` (that of ``spinecohort query``), decks by
``fe.models.virtual_model`` + ``write_model`` (the bytes ``spinecohort export`` writes), the continuous
patient model by ``personalize.build_model`` / ``PersonalizationModel.fit``, live shapes by the hex SSM's
linear formula (``HexSSM.sample``).  Nothing is written into the results or the bag; a model is named only
by an ID checked against the grid (``model_NNNNN``) or the known patients, never by a path.
"""

from __future__ import annotations

import logging
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.layout import Layout
from spinecohort.measure.spinopelvic import UNITS
from spinecohort.web.logic import (  # noqa: F401  (re-exported: the platform's one import place)
    MAX_ZIP_BYTES,
    MAX_ZIP_MODELS,
    PlatformError,
    bounded_zip,
    filter_mask,
    histogram_counts,
    nearest_models,
    parse_bound,
    xlsx_bytes,
)

log = logging.getLogger(__name__)

#: a grid model's ID as the table spells it; anything else from the browser is refused
MODEL_ID_RE = re.compile(r"^model_(\d{5})$")
#: patient IDs the platform accepts (and then only if the table knows them)
PATIENT_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")
#: formats of one model's download (the ``spinecohort export`` formats)
FORMATS = {"inp": "text/plain", "stl": "application/octet-stream", "vtu": "application/octet-stream"}
#: the clinical parameters offered as range filters, in this order when present (``TK_*``, ``DH_*`` expand)
FILTER_PARAMETERS = ("PI", "PT", "SS", "LL", "PI_minus_LL", "GT", "TPA", "TK_*", "Cobb", "SVA_*", "DH_*")
#: the parameters of "find my patient" (deg)
PATIENT_PARAMETERS = ("PI", "PT", "SS", "LL")


# ------------------------------------------------------------------------------------------- pure helpers
def unit_of(column: str) -> str:
    """Unit of a table column (deg, mm, %, points, SD, or '' for counts and flags)."""
    if re.fullmatch(r"w\d+|b\d+", column):
        return "SD"
    return UNITS.get(column, "")


def expand_parameters(columns, patterns=FILTER_PARAMETERS) -> list[str]:
    """The numeric filter columns present in ``columns``, patterns such as ``TK_*`` expanded in table order."""
    out = []
    for p in patterns:
        if p.endswith("*"):
            out += [c for c in columns if c.startswith(p[:-1]) and unit_of(c) in ("deg", "mm") and c not in out]
        elif p in columns:
            out.append(p)
    return out


def weight_columns(columns) -> list[str]:
    """Mode-weight columns ``w1``, ``w2``, ... (SD) in mode order."""
    return sorted((c for c in columns if re.fullmatch(r"w\d+", c)), key=lambda c: int(c[1:]))


# ------------------------------------------------------------------------------------------- the data
@dataclass
class Sources:
    """Where the platform reads from (all read-only) and the settings ``export`` takes."""

    origin: str  # "results DIR" or "release BAG", for the page
    table_csv: Path | None
    table_parquet: Path | None
    personalization_csv: Path | None
    patient_parameters: Path | None
    personalized_dir: Path | None
    store: Path | None
    ssm: Path
    hex_ssm: Path
    template: Path
    cohort: Path | None  # cohort.npz: faces (STL) and landmarks (the continuous patient fit)
    faces: Path | None  # release: faces.npy
    grid: dict
    hex_type: str
    fe: dict | None
    personalize: dict | None  # the config's personalize block (None: no continuous fit)
    workbook: Path | None = None  # Descriptive_List.xlsx: the whole cohort as a prepared workbook
    measure: dict = field(default_factory=lambda: {"vertical": [0.0, 0.0, 1.0], "c7_proxy": "extrapolated"})

    @classmethod
    def from_results(cls, results: str | Path, config: dict) -> Sources:
        L = Layout(results)
        opt = lambda p: Path(p) if Path(p).exists() else None  # noqa: E731
        m = config.get("measure", {})
        return cls(
            origin=f"results {Path(results).resolve()}",
            table_csv=opt(L.virtual_cohort_csv),
            table_parquet=opt(L.virtual_cohort_parquet),
            personalization_csv=opt(L.personalization_csv),
            patient_parameters=opt(L.patient_parameters),
            personalized_dir=opt(L.personalized_dir),
            store=opt(L.store),
            ssm=Path(L.ssm),
            hex_ssm=Path(L.hex_ssm),
            template=Path(L.template),
            cohort=opt(L.cohort),
            faces=None,
            grid=config["grid"],
            hex_type=config["template"]["hex_type"],
            fe=config.get("fe"),
            personalize=config.get("personalize"),
            workbook=opt(L.descriptive_list),
            measure={
                "vertical": m.get("vertical_axis", [0.0, 0.0, 1.0]),
                "c7_proxy": m.get("c7_proxy", "extrapolated"),
            },
        )

    @classmethod
    def from_release(cls, bag: str | Path) -> Sources:
        """A release bag read in place: the table, the decks and the model inputs are plain files of the
        bag's ``data/``; the store's archive parts are not needed (models are rebuilt from the model
        inputs exactly as ``spinecohort export --release`` does), so nothing is unpacked or written."""
        from spinecohort.release import release_model_inputs

        src = release_model_inputs(bag)
        data = Path(src["ssm"]).parent.parent
        opt = lambda p: p if p.exists() else None  # noqa: E731
        return cls(
            origin=f"release {Path(bag).resolve()}",
            table_csv=opt(data / "virtual_cohort.csv"),
            table_parquet=None,
            personalization_csv=opt(data / "personalized" / "personalization.csv"),
            patient_parameters=opt(data / "patients" / "parameters.csv"),
            personalized_dir=opt(data / "personalized"),
            store=None,
            ssm=src["ssm"],
            hex_ssm=src["hex_ssm"],
            template=src["template"],
            cohort=None,
            faces=src["faces"],
            grid=src["grid"],
            hex_type=src["hex_type"],
            fe=src["fe"],
            personalize=None,
            workbook=opt(data / "Descriptive_List.xlsx"),
        )


class CohortData:
    """The table, the models and the downloads of one results folder or release (read-only)."""

    def __init__(self, sources: Sources):
        from spinecohort.mesh.hex_ssm import HexSSM
        from spinecohort.mesh.template import HexTemplate
        from spinecohort.ssm.model import SSM
        from spinecohort.store.zarr_store import n_models

        self.src = sources
        self.missing: list[str] = []
        for what, p in (("SSM", sources.ssm), ("hex SSM", sources.hex_ssm), ("hex template", sources.template)):
            if not Path(p).is_file():
                raise PlatformError(f"{p} does not exist ({what}); run the pipeline (snakemake) first")
        self.ssm = SSM.load(sources.ssm)
        self.hex_ssm = HexSSM.load(sources.hex_ssm)
        self.template = HexTemplate.load(sources.template)
        self.n_modes = int(sources.grid["n_modes"])
        self.levels = list(sources.grid["levels"])
        self.n_grid = n_models(self.n_modes, self.levels)
        self.virtual = self._read_virtual()
        self.personalization = self._read_personalization()
        self.deck_only = self._deck_only_patients()
        self.table = self._combined_table()
        self.weights = weight_columns(self.table.columns)
        self.parameters = expand_parameters(self.table.columns)
        self.flags = [c for c in ("distracted", "repaired") if c in self.table.columns]
        self._faces = None
        self._fit_model = None
        if sources.store is None and sources.origin.startswith("results"):
            self.missing.append("the cohort store (cohort.zarr): models are rebuilt from the hex SSM")

    # ------------------------------------------------------------------- tables
    def _read_virtual(self) -> pd.DataFrame:
        s = self.src
        if s.table_parquet is not None:
            t = pd.read_parquet(s.table_parquet)
        elif s.table_csv is not None:
            t = pd.read_csv(s.table_csv)
        else:
            self.missing.append("the virtual-cohort table (virtual_cohort.csv): filtering is off")
            return pd.DataFrame({"model_id": pd.Series(dtype=str)})
        t = t.copy()  # one consolidated block (pandas' CSV reader leaves a wide table fragmented)
        extra = {"kind": "virtual"}
        if "distraction_mm" in t.columns and "distracted" not in t.columns:
            extra["distracted"] = t["distraction_mm"].to_numpy(float) > 0  # the disc-contact distraction moved it
        if "repaired" in t.columns:
            extra["repaired"] = t["repaired"].fillna(False).astype(bool)
        return t.assign(**extra)

    def _read_personalization(self) -> pd.DataFrame | None:
        s = self.src
        if s.personalization_csv is None:
            self.missing.append(
                "personalized/personalization.csv (the patients' fitted weights and fit errors): patients are "
                "listed by their decks in personalized/ only, if any, with their measured parameters"
            )
            return None
        p = pd.read_csv(s.personalization_csv, dtype={"ID": str})
        if "method" in p.columns:
            p = p[p["method"] == "fit"]
        return p.reset_index(drop=True)

    def _combined_table(self) -> pd.DataFrame:
        """The virtual cohort plus one row per personalized patient model (its achieved parameters, weights
        as ``w<i>``), in one table; ``kind`` tells them apart."""
        if self.deck_only:  # decks without the fit table: the patients' measured values (not the model's)
            rows = pd.DataFrame({"model_id": self.deck_only, "kind": "patient deck (measured values)"})
            if self.src.patient_parameters is not None:
                m = pd.read_csv(self.src.patient_parameters, dtype={"ID": str}).set_index("ID")
                cols = [c for c in m.columns if c in self.virtual.columns and c != "model_id"]
                rows = rows.join(m[cols], on="model_id")
            return pd.concat([self.virtual, rows], ignore_index=True)
        if self.personalization is None or self.personalization.empty:
            return self.virtual.reset_index(drop=True)
        p = self.personalization
        rows = pd.DataFrame({"model_id": p["ID"].astype(str), "kind": "personalized"})
        for c in p.columns:
            if re.fullmatch(r"b\d+", c):
                rows[f"w{c[1:]}"] = p[c].to_numpy(float)
        # the parameters the fitted model achieved (personalize measures them on the model)
        for c in p.columns:
            if c.endswith("_achieved"):
                rows[c.removesuffix("_achieved")] = p[c].to_numpy(float)
        for c in ("invalid_after", "min_sj_after", "distraction_mm"):
            if c in p.columns:
                rows[c] = p[c].to_numpy(float)
        if "distraction_mm" in rows.columns:
            rows["distracted"] = rows["distraction_mm"].to_numpy(float) > 0
        if "nodes_moved" in p.columns:
            rows["repaired"] = p["nodes_moved"].fillna(0).to_numpy(float) > 0
        return pd.concat([self.virtual, rows], ignore_index=True)

    @property
    def patient_ids(self) -> set[str]:
        """Patients with a fitted model: the personalization table's, else the decks in ``personalized/``
        (a release ships the decks without the table)."""
        if self.personalization is not None:
            return set(self.personalization["ID"].astype(str))
        return set(self.deck_only)

    def _deck_only_patients(self) -> list[str]:
        d = self.src.personalized_dir
        if self.personalization is not None or d is None:
            return []
        return sorted(p.stem for p in d.glob("*.inp") if PATIENT_ID_RE.fullmatch(p.stem))

    def units(self) -> dict[str, str]:
        return {c: unit_of(c) for c in self.table.columns}

    # ------------------------------------------------------------------- IDs
    def check_id(self, name) -> str:
        """``name`` if it is a grid model ID in range or a known patient ID, else PlatformError."""
        s = str(name).strip()
        m = MODEL_ID_RE.fullmatch(s)
        if m:
            if int(m.group(1)) >= self.n_grid:
                raise PlatformError(
                    f"{s} is outside the grid of {self.n_grid} models (model_00000 ... model_{self.n_grid - 1:05d})"
                )
            return s
        if PATIENT_ID_RE.fullmatch(s) and s in self.patient_ids:
            return s
        raise PlatformError(
            f"'{s[:40]}' is not a model ID (model_00000 ... model_{self.n_grid - 1:05d}) or a known patient ID"
        )

    def check_weights(self, weights) -> np.ndarray:
        w = np.asarray(weights, float)
        lim = float(max(abs(v) for v in self.levels))
        if w.ndim != 1 or len(w) > self.hex_ssm.fields.shape[0] or not np.all(np.isfinite(w)):
            raise PlatformError(f"mode weights must be at most {self.hex_ssm.fields.shape[0]} finite numbers")
        if np.any(np.abs(w) > lim + 1e-9):
            raise PlatformError(f"mode weights must lie within +-{lim:g} SD, got {np.round(w, 3).tolist()}")
        return w

    # ------------------------------------------------------------------- models
    def weights_of(self, name: str) -> np.ndarray:
        """Mode weights (SD) of a model or a patient's fitted model."""
        from spinecohort.store.zarr_store import weights_of

        name = self.check_id(name)
        if name.startswith("model_"):
            return np.asarray(weights_of(int(name[6:]), self.n_modes, self.levels), float)
        if self.personalization is None:
            return np.zeros(0)  # a release's deck: its weights are not recorded in the bag
        row = self.personalization[self.personalization["ID"].astype(str) == name].iloc[0]
        return np.array(
            [row[c] for c in sorted((c for c in row.index if re.fullmatch(r"b\d+", c)), key=lambda c: int(c[1:]))],
            float,
        )

    def model_points(self, name: str) -> np.ndarray:
        """All node coordinates (n_nodes, 3) mm of a model in the template's node order: a grid model from the
        store when there is one (the stored coordinates), else rebuilt as ``export`` builds it; a patient's
        fitted model as ``personalize`` builds its deck (or read from the release's deck)."""
        name = self.check_id(name)
        if name.startswith("model_"):
            if self.src.store is not None:
                from spinecohort.store.zarr_store import read_model

                _, hex_pts = read_model(self.src.store, int(name[6:]))
                return np.asarray(hex_pts, float)
            from spinecohort.fe.models import hex_points_checked

            return hex_points_checked(self.template, self.hex_ssm, self.weights_of(name))[0]
        if self.personalization is None:  # a release's deck: its *NODE block, in the template's node order
            from spinecohort.fe.export import read_deck_points

            try:
                return read_deck_points(self.src.personalized_dir / f"{name}.inp", self.template)
            except ValueError:
                raise PlatformError(f"{name}.inp does not have the template's {self.template.n_nodes} nodes") from None
        from spinecohort.personalize.cohort import personalized_hex

        row = self.personalization[self.personalization["ID"].astype(str) == name].iloc[0]
        posture = float(row["posture_deg"]) if "posture_deg" in row.index and np.isfinite(row["posture_deg"]) else 0.0
        return personalized_hex(self.template, self.hex_ssm, self.weights_of(name), posture, name=name)[0]

    def live_points(self, weights) -> np.ndarray:
        """Node coordinates (n_nodes, 3) mm of continuous weights by the hex SSM's linear formula (no contact
        distraction, no repair: the live preview; downloads apply both)."""
        return self.hex_ssm.sample(self.check_weights(weights))

    @property
    def faces(self) -> np.ndarray:
        if self._faces is None:
            if self.src.faces is not None:
                self._faces = np.load(self.src.faces, allow_pickle=False)
            elif self.src.cohort is not None:
                from spinecohort.cohort.loading import load_cohort_npz

                self._faces = load_cohort_npz(self.src.cohort).faces
            else:
                raise PlatformError("no triangulated faces (cohort.npz): the .stl download is not available")
        return self._faces

    # ------------------------------------------------------------------- downloads
    def model_file(self, name: str, fmt: str) -> tuple[str, bytes]:
        """(file name, bytes) of a model's download: for a grid model exactly what ``spinecohort export``
        writes (``virtual_model`` + ``write_model``, the same materials); for a patient, its deck from
        ``personalized/``."""
        from spinecohort.fe.materials import materials_from_config
        from spinecohort.fe.models import virtual_model, write_model

        name = self.check_id(name)
        if fmt not in FORMATS:
            raise PlatformError(f"unknown format '{str(fmt)[:10]}' (inp | stl | vtu)")
        if not name.startswith("model_"):
            deck = None if self.src.personalized_dir is None else self.src.personalized_dir / f"{name}.inp"
            if fmt != "inp" or deck is None or not deck.is_file():
                raise PlatformError(
                    f"{name}: only its .inp deck is offered, and it is {'not ' if deck is None or not deck.is_file() else ''}in personalized/"
                )
            return f"{name}.inp", deck.read_bytes()
        vm = virtual_model(name, self.ssm, self.hex_ssm, self.template, self.n_modes, self.levels)
        with tempfile.TemporaryDirectory(prefix="spinecohort-web-") as tmp:
            out = Path(tmp) / f"{name}.{fmt}"
            faces = self.faces if fmt == "stl" else None
            write_model(
                vm, fmt, out, self.template, faces, self.src.hex_type, materials=materials_from_config(self.src.fe)
            )
            return out.name, out.read_bytes()

    def decks_zip(self, names: list[str], progress=None, max_models: int = MAX_ZIP_MODELS) -> bytes:
        """A bounded zip of the decks (.inp) of ``names`` (each validated)."""
        names = [self.check_id(n) for n in names]
        return bounded_zip(
            [f"{n}.inp" for n in names],
            lambda f: self.model_file(f.removesuffix(".inp"), "inp")[1],
            max_models=max_models,
            progress=progress,
        )

    @property
    def workbook(self) -> Path | None:
        """The run's prepared workbook of the whole cohort (``Descriptive_List.xlsx``), if there is one."""
        return self.src.workbook

    def workbook_bytes(self) -> bytes:
        if self.src.workbook is None:
            raise PlatformError("this folder has no Descriptive_List.xlsx (the whole cohort as a workbook)")
        return Path(self.src.workbook).read_bytes()

    def table_file(self, mask: np.ndarray, fmt: str) -> tuple[str, bytes]:
        """The filtered table as CSV or xlsx, headers with units (``PI [deg]``)."""
        from spinecohort.measure.spinopelvic import parameter_table_header

        t = parameter_table_header(self.table.loc[np.asarray(mask, bool)])
        if fmt == "csv":
            return "virtual_cohort_selection.csv", t.to_csv(index=False, float_format="%.6f").encode()
        if fmt == "xlsx":
            return "virtual_cohort_selection.xlsx", xlsx_bytes(t, "selection")
        raise PlatformError(f"unknown table format '{str(fmt)[:10]}' (csv | xlsx)")

    # ------------------------------------------------------------------- find my patient
    def check_targets(self, targets: dict) -> dict[str, float]:
        """PI/PT/SS/LL typed in the page (any subset; '' = not given) -> targets with PI = PT + SS enforced."""
        from spinecohort.personalize.parameters import complete_pelvic_targets

        given = {}
        for k in PATIENT_PARAMETERS:
            v = parse_bound(targets.get(k), k)
            if v is not None:
                if not -90.0 <= v <= 150.0:
                    raise PlatformError(f"{k} = {v:g} deg is outside -90 ... 150 deg")
                given[k] = v
        if not given:
            raise PlatformError("give at least one of PI, PT, SS, LL (deg)")
        try:
            return complete_pelvic_targets(given, source="find my patient")
        except ValueError as exc:
            raise PlatformError(str(exc)) from None

    def nearest(self, targets: dict[str, float], k: int = 5) -> pd.DataFrame:
        v = self.virtual
        cols = [c for c in targets if c in v.columns]
        if not cols:
            raise PlatformError("the virtual-cohort table is missing: no grid models to compare with")
        return nearest_models(v, {c: targets[c] for c in cols}, k)

    @property
    def can_fit(self) -> bool:
        return self.src.personalize is not None and self.src.cohort is not None

    def fit(self, targets: dict[str, float]):
        """The continuous personalized model of ``targets`` (``personalize``'s fit, as ``spinecohort
        personalize`` runs it): FitResult with weights, posture and the achieved parameters."""
        if not self.can_fit:
            raise PlatformError("the continuous fit needs the results' cohort.npz and the config's personalize block")
        if self._fit_model is None:
            from spinecohort.cohort.landmarks import Landmarks
            from spinecohort.personalize.cohort import Settings, build_model

            settings = Settings.from_config(self.src.personalize, self.n_modes)
            self._fit_model = build_model(self.ssm, Landmarks.from_cohort(self.src.cohort), settings, self.src.measure)
        return self._fit_model.fit(targets)

    def fitted_deck(self, targets: dict[str, float], res) -> bytes:
        """The .inp deck of a continuous fit, composed as ``spinecohort personalize --out`` composes it
        (``personalized_hex``, ``fe_model``, ``write_inp``, the same heading): the same bytes."""
        heading = (
            f"spinecohort personalized model: targets {targets}, weights (SD) "
            f"{np.round(res.weights, 4).tolist()}, posture {res.posture_deg:.3f} deg"
        )
        return self.weights_deck(res.weights, res.posture_deg, heading)

    def weights_deck(self, weights, posture_deg: float = 0.0, heading: str | None = None) -> bytes:
        """The .inp deck of continuous mode ``weights`` (SD): the hex SSM's shape with the contact
        distraction, the Jacobian check and repair, turned by ``posture_deg`` (``personalized_hex``), in the
        run's materials (``fe_model`` + ``write_inp``)."""
        from spinecohort.fe.export import fe_model
        from spinecohort.fe.materials import materials_from_config
        from spinecohort.fe.writers import write_inp
        from spinecohort.personalize.cohort import personalized_hex

        w = self.check_weights(weights)
        heading = heading or f"spinecohort model of shape-mode weights (SD) {np.round(w, 4).tolist()}"
        try:
            pts, _ = personalized_hex(self.template, self.hex_ssm, w, posture_deg, name="personalized model")
        except ValueError as exc:  # RepairError: a shape that cannot be made valid gets no deck
            raise PlatformError(str(exc)) from None
        fe = fe_model(
            self.template,
            pts,
            hex_type=self.src.hex_type,
            heading=heading,
            materials=materials_from_config(self.src.fe),
        )
        with tempfile.TemporaryDirectory(prefix="spinecohort-web-") as tmp:
            out = Path(tmp) / "model.inp"
            write_inp(fe, out, provenance=heading)
            return out.read_bytes()


def open_data(
    results: str | Path | None = None, release: str | Path | None = None, config: str | Path | None = None
) -> CohortData:
    """The platform's data: ``release`` (a bag folder) or ``results`` (default: the config's)."""
    if release is not None:
        return CohortData(Sources.from_release(release))
    import yaml

    cfg_path = Path(config or "config/config.yaml")
    if not cfg_path.is_file():
        raise PlatformError(f"{cfg_path} does not exist: give --config (grid, template and fe settings) or --release")
    cfg = yaml.safe_load(cfg_path.read_text())
    r = Path(results or cfg["results"])
    if not r.is_dir():
        raise PlatformError(f"{r} is not a results folder; run snakemake first, or serve a release with --release")
    return CohortData(Sources.from_results(r, cfg))


def describe(data: CohortData) -> str:
    """One line for the page header: the source's kind and folder name (never the server's path) and counts."""
    n_p = int((data.table["kind"] != "virtual").sum()) if "kind" in data.table.columns else 0
    kind, _, where = data.src.origin.partition(" ")
    return f"{kind} {Path(where).name}: {len(data.virtual):,} virtual models, {n_p} patient models"
