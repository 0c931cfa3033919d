"""The state and the controllers of one browser session of ``spinecohort serve``.

One :class:`Platform` is one user's page: its filters, its selection, its sliders, its search and its
downloads.  ``launcher`` runs one such page per browser session in its own process, forked from a parent
that holds the data (:class:`~spinecohort.web.data.CohortData`, read-only), so sessions never see each
other's state.  Requests the data layer refuses (``PlatformError``) become a message in the page, the
next successful action clears it, and the server keeps serving.
"""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
import pandas as pd

from spinecohort.web.data import MAX_ZIP_MODELS, CohortData, PlatformError, describe
from spinecohort.web.labels import explain, gap_words, label, label_with_unit
from spinecohort.web.logic import filter_mask, histogram_counts, histogram_svg, parse_bound, parse_more_ranges
from spinecohort.web.scene import Scene

log = logging.getLogger(__name__)

#: range filters with their own min / max fields (any numeric column can be filtered in "more ranges")
MAIN_RANGES = ("PI", "PT", "SS", "LL", "PI_minus_LL", "GT", "TPA", "TK_T4T12", "Cobb", "SVA_T1")
#: columns of the table, in this order when present and not empty (the rest is in the downloads)
TABLE_COLUMNS = (
    "model_id",
    "kind",
    "PI",
    "PT",
    "SS",
    "LL",
    "PI_minus_LL",
    "GT",
    "TPA",
    "TK_T4T12",
    "Cobb",
    "SVA_T1",
    "DH_L4-L5",
    "GAP",
    "GAP_category",
    "weights",
    "repaired",
    "distracted",
)
#: parameters drawn as live histograms, and shown in the parameter panel
HISTOGRAMS = ("PI", "PT", "SS", "LL", "PI_minus_LL", "TPA", "GT", "Cobb", "SVA_T1")
PANEL = (
    *HISTOGRAMS,
    "TK_T4T12",
    "GAP",
    "GAP_assumed_age",
    "GAP_category",
    "min_sj_after",
    "invalid_after",
    "repaired",
    "distracted",
)
MAX_SLIDERS = 5
FLAG_CHOICES = ["any", "yes", "no"]
#: rows per table page; no "all": 16,807 rows of 20 columns are too many for the browser to draw at once
PAGE_SIZES = (10, 15, 25, 50, 100)
DEFAULT_PAGE_SIZE = 15
#: model download formats by what is on screen: a grid model, a patient's deck, a live or fitted shape
FORMATS_OF = {"grid": ["inp", "stl", "vtu"], "patient": ["inp"], "live": ["inp"], "fit": ["inp"], "": []}


def _cell(v):
    """A table value for the page: rounded floats, None for NaN, yes/no for flags, plain Python types."""
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        return None if not np.isfinite(v) else round(float(v), 2)
    if isinstance(v, (np.integer,)):
        return int(v)
    return v if v is None or isinstance(v, (int, str)) else str(v)


def table_rows(sub: pd.DataFrame, columns: list[str], weights: list[str]) -> list[dict]:
    """Rows of the page's table: rounded values, GAP categories in words, the mode weights in one column."""
    out = []
    w = np.round(sub[weights].to_numpy(float), 2) if weights else np.zeros((len(sub), 0))
    plain = [c for c in columns if c != "weights"]
    for k, r in enumerate(sub[plain].itertuples(index=False, name=None)):
        row = {c: _cell(v) for c, v in zip(plain, r)}
        if "GAP_category" in row:
            row["GAP_category"] = gap_words(row["GAP_category"])
        if "weights" in columns:
            row["weights"] = " ".join(f"{x:+.2f}" if np.isfinite(x) else "–" for x in w[k]) if len(w[k]) else ""
        out.append(row)
    return out


class Platform:
    """State, controllers and layout of one user's page over one CohortData."""

    def __init__(self, data: CohortData, server=None, max_zip: int = MAX_ZIP_MODELS, topology: dict | None = None):
        from trame.app import get_server

        from spinecohort.web.labels import empty_columns

        self.data = data
        self.max_zip = int(max_zip)
        self.server = server or get_server(client_type="vue3")
        self.state, self.ctrl = self.server.state, self.server.controller
        t = data.table
        empty = set(empty_columns(t, [c for c in t.columns if c != "model_id"]))
        self.ranges = [c for c in (*MAIN_RANGES, *data.weights) if c in t.columns and c not in empty]
        self.columns = [
            c for c in TABLE_COLUMNS if (c in t.columns and c not in empty) or (c == "weights" and data.weights)
        ]
        self.hist_params = [c for c in HISTOGRAMS if c in t.columns and c not in empty]
        self.panel = [c for c in PANEL if c in t.columns and c not in empty]
        self.n_sliders = min(MAX_SLIDERS, data.hex_ssm.fields.shape[0])
        self.mask = np.ones(len(t), bool)
        self.shown_weights = np.zeros(self.n_sliders)
        self._fit = self._fit_targets = None
        self._filter_error = False
        self.scene = Scene(data.template, data.hex_ssm.mean, topology=topology)
        self._init_state()
        from spinecohort.web.page import build_page

        self.layout = build_page(self)
        self._register()
        self.apply_filter()

    # --------------------------------------------------------------------------- state
    def _init_state(self) -> None:
        s, d = self.state, self.data
        gap = (
            sorted(d.table["GAP_category"].dropna().astype(str).unique().tolist(), key=lambda c: "P MD SD".find(c))
            if "GAP_category" in self.columns
            else []
        )
        s.update(
            {
                "trame__title": "spinecohort platform",
                "title": describe(d),
                "missing": d.missing,
                "message": "",
                "message_kind": "error",
                "f_other": "",
                "f_gap": [],
                "gap_choices": [{"title": gap_words(c), "value": c} for c in gap if c],
                "f_kind": "all",
                "kind_choices": ["all", *sorted(d.table["kind"].unique().tolist())],
                "flag_choices": FLAG_CHOICES,
                "flags": d.flags,
                "n_match": len(d.table),
                "n_total": len(d.table),
                "filter_ms": 0.0,
                "headers": [
                    {
                        "title": "Shape-mode weights (SD)" if c == "weights" else label_with_unit(c),
                        "key": c,
                        "sortable": c != "weights",
                        "hover": explain("w1") if c == "weights" else explain(c),
                    }
                    for c in self.columns
                ],
                "rows": [],
                "page": 1,
                "per_page": DEFAULT_PAGE_SIZE,
                "page_sizes": list(PAGE_SIZES),
                "sort_by": [],
                "hist_svg": "",
                "model_input": "",
                "shown_key": "",  # what the 3D view shows: a model ID, "live:<weights>" or "fit"
                "shown_kind": "",  # grid | patient | live | fit | '' (the mean)
                "shown_file": "",  # the download's file name without suffix
                "shown": "the mean model (all shape-mode weights 0 SD)",
                "dl_formats": [],
                "params": [],
                "slider_names": [f"w{i + 1}" for i in range(self.n_sliders)],
                "slider_lim": float(max(abs(v) for v in d.levels)),
                "live_ms": 0.0,
                "overlay_input": "",
                "overlay_label": "",
                "pat_PI": "",
                "pat_PT": "",
                "pat_SS": "",
                "pat_LL": "",
                "nearest": [],
                "fit_text": "",
                "fit_weights": [],
                "can_fit": d.can_fit,
                "zip_progress": 0,
                "zip_busy": False,
                "zip_text": "",
                "max_zip": self.max_zip,
                "has_workbook": d.workbook is not None,
            }
        )
        for c in self.ranges:
            s[f"f_{c}_lo"] = ""
            s[f"f_{c}_hi"] = ""
        for f in d.flags:
            s[f"f_{f}"] = "any"
        for i in range(self.n_sliders):
            s[f"w_{i}"] = 0.0

    def error(self, exc: Exception) -> None:
        self.state.message_kind = "error"
        self.state.message = str(exc)

    def ok(self) -> None:
        """A successful action: an earlier message no longer describes the page."""
        self.state.message = ""

    # --------------------------------------------------------------------------- filter and table
    def current_filters(self) -> tuple[dict, dict, dict]:
        s = self.state
        ranges = {}
        for c in self.ranges:
            lo, hi = parse_bound(s[f"f_{c}_lo"], f"{label(c)} min"), parse_bound(s[f"f_{c}_hi"], f"{label(c)} max")
            if lo is not None and hi is not None and lo > hi:
                raise PlatformError(f"{label(c)}: min {lo:g} exceeds max {hi:g}")
            if (lo, hi) != (None, None):
                ranges[c] = (lo, hi)
        more = parse_more_ranges(s.f_other)
        numeric = set(self.data.table.select_dtypes("number").columns)
        bad = [c for c in more if c not in numeric]
        if bad:
            raise PlatformError(f"no numeric column {bad[0]!r}; e.g. TK_T1T12, DH_L4-L5, w1, min_sj_after")
        ranges.update(more)
        cats = {"GAP_category": list(s.f_gap or [])} if "GAP_category" in self.columns else {}
        if s.f_kind != "all":
            cats["kind"] = [s.f_kind]
        flags = {f: {"any": None, "yes": True, "no": False}.get(s[f"f_{f}"]) for f in self.data.flags}
        return ranges, cats, flags

    def apply_filter(self, **_) -> None:
        try:
            t0 = time.perf_counter()
            ranges, cats, flags = self.current_filters()
            self.mask = filter_mask(self.data.table, ranges, cats, flags)
            self.state.filter_ms = round(1e3 * (time.perf_counter() - t0), 2)
        except PlatformError as exc:
            self.error(exc)
            self._filter_error = True
            return
        if self._filter_error:  # the filter is valid again: its message is obsolete
            self.ok()
            self._filter_error = False
        self.state.n_match = int(self.mask.sum())
        self.state.page = 1
        self.update_rows()
        self.update_histograms()

    def update_rows(self, **_) -> None:
        s, t = self.state, self.data.table
        idx = np.flatnonzero(self.mask)
        for sb in reversed(list(s.sort_by or [])):
            key = sb.get("key") if isinstance(sb, dict) else None
            if key in self.columns and key != "weights":
                vals = t[key].to_numpy()[idx]
                o = np.argsort(
                    pd.Series(vals).fillna(-np.inf if vals.dtype.kind == "f" else "").to_numpy(), kind="stable"
                )
                idx = idx[o[::-1]] if sb.get("order") == "desc" else idx[o]
        per = int(s.per_page) if s.per_page in PAGE_SIZES else DEFAULT_PAGE_SIZE
        page = max(1, int(s.page or 1))
        sel = idx[(page - 1) * per : page * per]
        s.rows = table_rows(t.iloc[sel], self.columns, self.data.weights)

    def on_options(self, options) -> None:
        """The table's page, page size or sort changed (values checked by ``validate``)."""
        if isinstance(options, dict):
            self.state.page = int(options.get("page", 1) or 1)
            per = options.get("itemsPerPage", DEFAULT_PAGE_SIZE)
            self.state.per_page = per if per in PAGE_SIZES else DEFAULT_PAGE_SIZE
            self.state.sort_by = options.get("sortBy", [])
        self.update_rows()

    def update_histograms(self) -> None:
        t = self.data.table
        hists = {p: histogram_counts(t[p].to_numpy(float), self.mask) for p in self.hist_params}
        self.state.hist_svg = histogram_svg(hists, {p: label_with_unit(p) for p in hists})

    # --------------------------------------------------------------------------- models in 3D
    def _panel_rows(self, name: str) -> list[dict]:
        row = self.data.table[self.data.table["model_id"] == name]
        if row.empty:
            return []
        r = row.iloc[0]
        out = []
        for c in self.panel:
            v = _cell(r[c])
            if c == "GAP_category":
                v = gap_words(v)
            if v is None or v == "":
                continue  # a blank line says nothing: the value is not measured for this model
            out.append(
                {"key": c, "name": label(c), "value": v, "unit": self.data.units().get(c, ""), "hover": explain(c)}
            )
        return out

    def _show(self, key: str, kind: str, pts: np.ndarray, weights: np.ndarray, text: str, params: list[dict]) -> None:
        """Put a shape on screen and make the panel and the downloads belong to it."""
        s = self.state
        self.shown_weights = np.zeros(self.n_sliders)
        self.shown_weights[: min(len(weights), self.n_sliders)] = weights[: self.n_sliders]
        s.shown_key, s.shown_kind, s.shown, s.params = key, kind, text, params
        s.shown_file = {
            "live": "shape_w" + "_".join(f"{x:+.2f}" for x in self.shown_weights),
            "fit": "personalized",
        }.get(kind, key)
        s.dl_formats = FORMATS_OF[kind]
        for i in range(self.n_sliders):
            s[f"w_{i}"] = float(self.shown_weights[i])
        self.scene.show(pts)
        self.ok()
        self.ctrl.view_update()

    def select(self, name=None) -> None:
        """Show a model (grid ID or patient ID typed or clicked) and its parameters."""
        name = self.state.model_input if name is None else name
        try:
            name = self.data.check_id(name)
            pts = self.data.model_points(name)
            w = self.data.weights_of(name)
        except PlatformError as exc:
            self.error(exc)
            return
        except Exception as exc:  # e.g. a model that cannot be repaired: say so, keep serving
            log.warning("showing %s: %s: %s", name, type(exc).__name__, exc)
            self.error(PlatformError(f"{name}: {type(exc).__name__}: {exc}"))
            return
        self.state.model_input = name
        kind = "grid" if name.startswith("model_") else "patient"
        ws = f"shape-mode weights {np.round(w, 2).tolist()} SD" if len(w) else "weights not recorded in a release"
        self._show(name, kind, pts, w, f"{name} ({ws})", self._panel_rows(name))

    def on_slider(self, **_) -> None:
        s = self.state
        w = np.array([float(s[f"w_{i}"]) for i in range(self.n_sliders)])
        if np.allclose(w, self.shown_weights, atol=1e-9):
            return  # set by _show() (the shape on screen) or unchanged
        t0 = time.perf_counter()
        try:
            pts = self.data.live_points(w)
        except PlatformError as exc:
            self.error(exc)
            return
        key = "live:" + ",".join(f"{x:.4f}" for x in w)
        text = f"live shape: shape-mode weights {np.round(w, 2).tolist()} SD (hex SSM formula)"
        self._show(key, "live", pts, w, text, [])
        s.live_ms = round(1e3 * (time.perf_counter() - t0), 1)

    def set_overlay(self, which: str) -> None:
        s = self.state
        try:
            if which == "none":
                self.scene.overlay(None)
                s.overlay_label = ""
            elif which == "mean":
                self.scene.overlay(self.data.hex_ssm.mean)
                s.overlay_label = "overlay: the mean model"
            elif which == "id":
                name = self.data.check_id(s.overlay_input)
                self.scene.overlay(self.data.model_points(name))
                s.overlay_label = f"overlay: {name}"
            else:
                raise PlatformError(f"unknown overlay {str(which)[:10]!r}")
        except PlatformError as exc:
            self.error(exc)
            return
        self.ok()
        self.ctrl.view_update()

    # --------------------------------------------------------------------------- find my patient
    async def find_patient(self) -> None:
        s = self.state
        try:
            targets = self.data.check_targets({k: s[f"pat_{k}"] for k in ("PI", "PT", "SS", "LL")})
            near = self.data.nearest(targets, 5)
        except PlatformError as exc:
            self.error(exc)
            return
        self.ok()
        cols = list(targets)
        s.nearest = [
            {
                "model_id": r["model_id"],
                "distance": round(float(r["distance"]), 2),
                "values": "  ".join(f"{c} {r[c]:.1f}°" for c in cols if np.isfinite(r[c])),
            }
            for _, r in near.iterrows()
        ]
        s.fit_weights = []
        if not self.data.can_fit:
            s.fit_text = "continuous fit not available here (it needs the results' cohort.npz and a config)"
            return
        s.fit_text = "fitting the continuous model ..."
        s.flush()
        loop = asyncio.get_running_loop()
        try:
            res = await loop.run_in_executor(None, self.data.fit, targets)
        except (PlatformError, ValueError) as exc:
            self.error(exc)
            s.fit_text = ""
            return
        err = ", ".join(f"{p} {res.achieved[p] - v:+.1f}°" for p, v in targets.items() if p in res.achieved)
        s.fit_weights = [float(x) for x in res.weights]
        self._fit, self._fit_targets = res, targets
        s.fit_text = (
            f"continuous model: weights {np.round(res.weights, 2).tolist()} SD, posture {res.posture_deg:.1f}°; "
            f"fit error (achieved − target): {err}"
        )

    def show_fit(self) -> None:
        from spinecohort.personalize.cohort import personalized_hex

        res = self._fit
        if res is None:
            self.error(PlatformError("find a patient first"))
            return
        pts, _ = personalized_hex(self.data.template, self.data.hex_ssm, res.weights, res.posture_deg, name="fit")
        params = [
            {
                "key": p,
                "name": f"{label(p)} (achieved)",
                "value": round(float(v), 2),
                "unit": "deg",
                "hover": explain(p),
            }
            for p, v in res.achieved.items()
            if np.isfinite(v)
        ]
        text = f"continuous personalized model (weights {np.round(res.weights, 2).tolist()} SD)"
        self._show("fit", "fit", pts, np.asarray(res.weights), text, params)

    # --------------------------------------------------------------------------- downloads
    def _refuse(self, exc: Exception, what: str) -> None:
        """A refused download: the message in the page and one log line; the client gets no file."""
        with self.state:
            self.error(exc)
        log.info("refused %s: %s", what, exc)

    async def download_shown(self, key, fmt):
        """The shape on screen as ``fmt``: a grid model as ``export`` writes it, a patient's deck, or the
        deck of the live or fitted weights.  ``key`` is what the page showed when clicked: if the view has
        changed since, the click is refused rather than answered with another shape."""
        loop = asyncio.get_running_loop()
        s = self.state
        try:
            if key != s.shown_key or fmt not in s.dl_formats:
                raise PlatformError(f"{str(fmt)[:5]} of {str(key)[:40]!r} is not what the page shows; click again")
            if s.shown_kind in ("grid", "patient"):
                payload = (await loop.run_in_executor(None, self.data.model_file, key, fmt))[1]
            elif s.shown_kind == "fit":
                payload = await loop.run_in_executor(None, self.data.fitted_deck, self._fit_targets, self._fit)
            else:
                w = self.shown_weights.copy()
                payload = await loop.run_in_executor(None, self.data.weights_deck, w)
        except PlatformError as exc:
            self._refuse(exc, f"download {key!r} {fmt!r}")
            return None
        with s:
            self.ok()
        return payload

    def download_table(self, fmt):
        try:
            if fmt == "workbook":
                payload = self.data.workbook_bytes()
            else:
                payload = self.data.table_file(self.mask, fmt)[1]
        except PlatformError as exc:
            self._refuse(exc, f"table {fmt!r}")
            return None
        self.ok()
        return payload

    async def download_fit(self):
        """The deck of the last continuous fit (without showing it first)."""
        if self._fit is None:
            self._refuse(PlatformError("find a patient first"), "fit deck")
            return None
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(None, self.data.fitted_deck, self._fit_targets, self._fit)

    async def download_zip(self):
        s = self.state
        names = self.data.table.loc[self.mask, "model_id"].astype(str).tolist()
        loop = asyncio.get_running_loop()

        def progress(done, total):
            loop.call_soon_threadsafe(self._progress, done, total)

        with s:
            s.zip_busy, s.zip_progress, s.zip_text = True, 0, f"building 0 of {len(names)} decks"
        try:
            payload = await loop.run_in_executor(None, lambda: self.data.decks_zip(names, progress, self.max_zip))
        except PlatformError as exc:
            self._refuse(exc, "zip")
            return None
        finally:
            with s:
                s.zip_busy, s.zip_text = False, ""
        with s:
            self.ok()
        return payload

    def _progress(self, done, total):
        with self.state:
            self.state.zip_progress = round(100 * done / total)
            self.state.zip_text = f"building {done} of {total} decks"

    # --------------------------------------------------------------------------- wiring
    def filter_keys(self) -> list[str]:
        keys = [f"f_{x}_{b}" for x in self.ranges for b in ("lo", "hi")]
        return keys + ["f_other", "f_gap", "f_kind"] + [f"f_{f}" for f in self.data.flags]

    def _register(self) -> None:
        s, c = self.state, self.ctrl
        s.change(*self.filter_keys())(self.apply_filter)
        s.change(*[f"w_{i}" for i in range(self.n_sliders)])(self.on_slider)
        c.trigger("download_shown")(self.download_shown)
        c.trigger("download_table")(self.download_table)
        c.trigger("download_zip")(self.download_zip)
        c.trigger("download_fit")(self.download_fit)
