"""The trame page of ``spinecohort serve`` and its controllers.

One server process holds one :class:`~spinecohort.web.data.CohortData` (read-only) and one shared page
state: every browser tab connected to it sees the same filters and the same model (trame's model; run one
process per independent user).  Requests the data layer refuses (``PlatformError``) become a message in
the page; the server keeps serving.
"""

from __future__ import annotations

import asyncio
import logging
import math
import sys
import time

import numpy as np
import pandas as pd

from spinecohort.web.data import MAX_ZIP_MODELS, CohortData, PlatformError, describe, filter_mask, parse_bound
from spinecohort.web.scene import Scene

log = logging.getLogger(__name__)

#: range filters with their own min / max fields (any numeric column can be filtered in "more ranges")
MAIN_RANGES = ("PI", "PT", "SS", "LL", "PI_minus_LL", "GT", "TPA", "TK_T4T12", "Cobb", "SVA_T1")
#: columns of the table (the rest is in the downloads)
TABLE_COLUMNS = (
    "model_id",
    "kind",
    "w*",
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


def histogram_svg(hists: dict[str, dict], units: dict[str, str], width: int = 120, height: int = 60) -> str:
    """Small-multiple histograms as one inline SVG: per parameter the whole cohort (grey) and the current
    selection (blue) on the same count axis, so the selection shows as the part of the cohort it is."""
    cols = 3
    rows = math.ceil(len(hists) / cols) or 1
    cell_w, cell_h = width + 10, height + 30
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{cols * cell_w}" height="{rows * cell_h}" '
        'font-family="sans-serif" font-size="10">'
    ]
    for k, (name, h) in enumerate(hists.items()):
        x0, y0 = (k % cols) * cell_w + 5, (k // cols) * cell_h + 12
        top = max(int(h["all"].max()), 1)
        n = len(h["all"])
        bw = width / n
        unit = units.get(name, "")
        out.append(f'<text x="{x0}" y="{y0 - 2}">{name}{f" [{unit}]" if unit else ""}</text>')
        for i, (a, s) in enumerate(zip(h["all"], h["selected"])):
            ha, hs = height * a / top, height * s / top
            x = x0 + i * bw
            out.append(
                f'<rect x="{x:.1f}" y="{y0 + height - ha:.1f}" width="{bw:.1f}" height="{ha:.1f}" fill="#d0d0d0"/>'
            )
            if s:
                out.append(
                    f'<rect x="{x:.1f}" y="{y0 + height - hs:.1f}" width="{bw:.1f}" height="{hs:.1f}" fill="#2b6cb0"/>'
                )
        lo, hi = h["edges"][0], h["edges"][-1]
        out.append(f'<text x="{x0}" y="{y0 + height + 11}">{lo:.3g}</text>')
        out.append(f'<text x="{x0 + width}" y="{y0 + height + 11}" text-anchor="end">{hi:.3g}</text>')
    out.append("</svg>")
    return "".join(out)


def parse_more_ranges(text: str) -> dict[str, tuple[float | None, float | None]]:
    """``"TK_T1T12 30:50; DH_L4-L5 8:"`` -> {column: (lo, hi)} with ``measure.tables.parse_range`` (the
    grammar of ``spinecohort query``)."""
    from spinecohort.measure.tables import parse_range

    out = {}
    for part in str(text or "").replace(",", ";").split(";"):
        part = part.strip()
        if not part:
            continue
        name, _, rng = part.partition(" ")
        try:
            out[name] = parse_range(rng.strip(), name)
        except ValueError as exc:
            raise PlatformError(str(exc)) from None
    return out


def _cell(v):
    """A table value for the page: rounded floats, None for NaN, plain Python types."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (float, np.floating)):
        return None if not np.isfinite(v) else round(float(v), 2)
    if isinstance(v, (np.integer,)):
        return int(v)
    return v if v is None or isinstance(v, (int, str)) else str(v)


class Platform:
    """State, controllers and layout of the page over one CohortData."""

    def __init__(self, data: CohortData, server=None, max_zip: int = MAX_ZIP_MODELS):
        from trame.app import get_server

        self.data = data
        self.max_zip = int(max_zip)
        self.server = server or get_server(client_type="vue3")
        self.state, self.ctrl = self.server.state, self.server.controller
        t = data.table
        self.ranges = [c for c in (*MAIN_RANGES, *data.weights) if c in t.columns]
        self.columns = [c for p in TABLE_COLUMNS for c in (data.weights if p == "w*" else [p]) if c in t.columns]
        self.hist_params = [c for c in HISTOGRAMS if c in t.columns]
        self.n_sliders = min(MAX_SLIDERS, data.hex_ssm.fields.shape[0])
        self.mask = np.ones(len(t), bool)
        self.order = np.arange(len(t))
        self.selected: str | None = None
        self.selected_weights = np.zeros(self.n_sliders)
        mean = data.hex_ssm.mean
        self.scene = Scene(data.template, mean)
        self._init_state()
        self._build_ui()
        self._register()
        self.apply_filter()

    # --------------------------------------------------------------------------- state
    def _init_state(self) -> None:
        s, d = self.state, self.data
        units = d.units()
        s.update(
            {
                "title": describe(d),
                "missing": d.missing,
                "message": "",
                "message_kind": "error",
                "f_other": "",
                "f_gap": [],
                "gap_choices": sorted(d.table["GAP_category"].dropna().astype(str).unique().tolist())
                if "GAP_category" in d.table.columns
                else [],
                "f_kind": "all",
                "kind_choices": ["all", *sorted(d.table["kind"].unique().tolist())],
                "flag_choices": FLAG_CHOICES,
                "flags": d.flags,
                "n_match": len(d.table),
                "n_total": len(d.table),
                "filter_ms": 0.0,
                "headers": [
                    {"title": f"{c} [{units[c]}]" if units.get(c) else c, "key": c, "sortable": True}
                    for c in self.columns
                ],
                "rows": [],
                "page": 1,
                "per_page": 10,
                "sort_by": [],
                "hist_svg": "",
                "model_input": "",
                "selected_id": "",
                "shown": "the mean model (all weights 0 SD)",
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
                "max_zip": self.max_zip,
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

    def info(self, text: str) -> None:
        self.state.message_kind = "info"
        self.state.message = text

    # --------------------------------------------------------------------------- filter and table
    def current_filters(self) -> tuple[dict, dict, dict]:
        s = self.state
        ranges = {}
        for c in self.ranges:
            lo, hi = parse_bound(s[f"f_{c}_lo"], f"{c} min"), parse_bound(s[f"f_{c}_hi"], f"{c} max")
            if lo is not None and hi is not None and lo > hi:
                raise PlatformError(f"{c}: min {lo:g} exceeds max {hi:g}")
            if (lo, hi) != (None, None):
                ranges[c] = (lo, hi)
        more = parse_more_ranges(s.f_other)
        numeric = set(self.data.table.select_dtypes("number").columns)
        bad = [c for c in more if c not in numeric]
        if bad:
            raise PlatformError(f"no numeric column {bad[0]!r}; e.g. TK_T1T12, DH_L4-L5, w1, min_sj_after")
        ranges.update(more)
        cats = {"GAP_category": list(s.f_gap or [])} if "GAP_category" in self.data.table.columns else {}
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
        if getattr(self, "_filter_error", False):  # the filter is valid again: its message is obsolete
            self.state.message, self._filter_error = "", False
        self.state.n_match = int(self.mask.sum())
        self.state.page = 1
        self.update_rows()
        self.update_histograms()

    def update_rows(self, **_) -> None:
        s, t = self.state, self.data.table
        idx = np.flatnonzero(self.mask)
        for sb in reversed(list(s.sort_by or [])):
            key = sb.get("key") if isinstance(sb, dict) else None
            if key in self.columns:
                vals = t[key].to_numpy()[idx]
                o = np.argsort(
                    pd.Series(vals).fillna(-np.inf if vals.dtype.kind == "f" else "").to_numpy(), kind="stable"
                )
                idx = idx[o[::-1]] if sb.get("order") == "desc" else idx[o]
        per = max(1, min(int(s.per_page if s.per_page and s.per_page > 0 else 10), 100))
        page = max(1, int(s.page or 1))
        sel = idx[(page - 1) * per : page * per]
        sub = t.iloc[sel][self.columns]
        s.rows = [{c: _cell(v) for c, v in zip(self.columns, r)} for r in sub.itertuples(index=False, name=None)]

    def on_options(self, options) -> None:
        if isinstance(options, dict):
            self.state.page = options.get("page", 1)
            self.state.per_page = options.get("itemsPerPage", 10)
            self.state.sort_by = options.get("sortBy", [])
        self.update_rows()

    def update_histograms(self) -> None:
        from spinecohort.web.data import histogram_counts

        t = self.data.table
        hists = {p: histogram_counts(t[p].to_numpy(float), self.mask) for p in self.hist_params}
        self.state.hist_svg = histogram_svg(hists, self.data.units())

    # --------------------------------------------------------------------------- models in 3D
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
            log.exception("showing %s", name)
            self.error(PlatformError(f"{name}: {type(exc).__name__}: {exc}"))
            return
        self.selected = name
        self.selected_weights = np.zeros(self.n_sliders)
        self.selected_weights[: min(len(w), self.n_sliders)] = w[: self.n_sliders]
        s = self.state
        s.selected_id = name
        s.model_input = name
        s.message = ""
        for i in range(self.n_sliders):
            s[f"w_{i}"] = float(self.selected_weights[i])
        self.scene.show(pts)
        s.shown = f"{name} (weights {np.round(w, 3).tolist()} SD)"
        row = self.data.table[self.data.table["model_id"] == name]
        units = self.data.units()
        s.params = (
            []
            if row.empty
            else [
                {"name": c, "value": _cell(row.iloc[0][c]), "unit": units.get(c, "")} for c in PANEL if c in row.columns
            ]
        )
        self.ctrl.view_update()

    def on_slider(self, **_) -> None:
        s = self.state
        w = np.array([float(s[f"w_{i}"]) for i in range(self.n_sliders)])
        if np.allclose(w, self.selected_weights, atol=1e-9):
            return  # set by select() (the stored model is shown) or unchanged
        t0 = time.perf_counter()
        try:
            pts = self.data.live_points(w)
        except PlatformError as exc:
            self.error(exc)
            return
        self.scene.show(pts)
        self.ctrl.view_update()
        s.live_ms = round(1e3 * (time.perf_counter() - t0), 1)
        s.shown = f"live: hex SSM at weights {np.round(w, 2).tolist()} SD (linear formula)"
        self.selected, self.selected_weights = None, w

    def set_overlay(self, which: str) -> None:
        s = self.state
        try:
            if which == "none":
                self.scene.overlay(None)
                s.overlay_label = ""
            elif which == "mean":
                self.scene.overlay(self.data.hex_ssm.mean)
                s.overlay_label = "overlay: the mean model"
            else:
                name = self.data.check_id(s.overlay_input)
                self.scene.overlay(self.data.model_points(name))
                s.overlay_label = f"overlay: {name}"
        except PlatformError as exc:
            self.error(exc)
            return
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
        s.message = ""
        cols = list(targets)
        s.nearest = [
            {"model_id": r["model_id"], "distance": round(float(r["distance"]), 3), **{c: _cell(r[c]) for c in cols}}
            for _, r in near.iterrows()
        ]
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
        err = ", ".join(f"{p} {res.achieved[p] - v:+.2f}" for p, v in targets.items() if p in res.achieved)
        s.fit_weights = [float(x) for x in res.weights]
        self._fit, self._fit_targets = res, targets
        s.fit_text = (
            f"continuous model: weights {np.round(res.weights, 2).tolist()} SD, posture {res.posture_deg:.2f} deg; "
            f"fit error (achieved - target, deg): {err}"
        )

    def show_fit(self) -> None:
        from spinecohort.personalize.cohort import personalized_hex

        res = getattr(self, "_fit", None)
        if res is None:
            self.error(PlatformError("find a patient first"))
            return
        pts, _ = personalized_hex(self.data.template, self.data.hex_ssm, res.weights, res.posture_deg, name="fit")
        self.scene.show(pts)
        self.selected = None
        self.state.shown = f"continuous personalized model (weights {np.round(res.weights, 2).tolist()} SD)"
        self.ctrl.view_update()

    # --------------------------------------------------------------------------- downloads
    async def download_model(self, name, fmt):
        loop = asyncio.get_running_loop()
        try:
            _, payload = await loop.run_in_executor(None, self.data.model_file, name, fmt)
        except PlatformError as exc:
            with self.state:
                self.error(exc)
            raise
        return payload

    async def download_fit(self):
        res = getattr(self, "_fit", None)
        if res is None:
            with self.state:
                self.error(PlatformError("find a patient first"))
            raise PlatformError("no fit")
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(None, self.data.fitted_deck, self._fit_targets, res)

    def download_table(self, fmt):
        try:
            return self.data.table_file(self.mask, fmt)[1]
        except PlatformError as exc:
            with self.state:
                self.error(exc)
            raise

    async def download_zip(self):
        s = self.state
        t = self.data.table
        names = t.loc[self.mask, "model_id"].astype(str).tolist()
        if len(names) > self.max_zip:
            with s:
                self.error(PlatformError(f"{len(names)} models selected; a zip holds at most {self.max_zip}"))
            raise PlatformError("too many models")
        loop = asyncio.get_running_loop()

        def progress(done, total):
            loop.call_soon_threadsafe(self._progress, done, total)

        with s:
            s.zip_busy, s.zip_progress = True, 0
        try:
            return await loop.run_in_executor(None, lambda: self.data.decks_zip(names, progress, self.max_zip))
        except PlatformError as exc:
            with s:
                self.error(exc)
            raise
        finally:
            with s:
                s.zip_busy = False

    def _progress(self, done, total):
        with self.state:
            self.state.zip_progress = round(100 * done / total)

    # --------------------------------------------------------------------------- wiring
    def _register(self) -> None:
        s, c = self.state, self.ctrl
        keys = [f"f_{x}_{b}" for x in self.ranges for b in ("lo", "hi")]
        keys += ["f_other", "f_gap", "f_kind"] + [f"f_{f}" for f in self.data.flags]
        s.change(*keys)(self.apply_filter)
        s.change(*[f"w_{i}" for i in range(self.n_sliders)])(self.on_slider)
        c.trigger("download_model")(self.download_model)
        c.trigger("download_table")(self.download_table)
        c.trigger("download_zip")(self.download_zip)
        c.trigger("download_fit")(self.download_fit)

    def _build_ui(self) -> None:
        from trame.ui.vuetify3 import SinglePageWithDrawerLayout
        from trame.widgets import html
        from trame.widgets import vtk as vtk_widgets
        from trame.widgets import vuetify3 as v

        dense = {"density": "compact", "hide_details": True, "variant": "outlined"}
        with SinglePageWithDrawerLayout(self.server, width=430) as layout:
            layout.title.set_text("spinecohort platform")
            with layout.toolbar:
                v.VSpacer()
                html.Div("{{ title }}", classes="text-caption mr-4", id="data-title")
            with layout.drawer:
                with v.VContainer(classes="pa-2"):
                    html.Div("Filter (bounds inclusive)", classes="text-subtitle-2")
                    with v.VRow(dense=True):
                        for c in self.ranges:
                            unit = self.data.units().get(c, "")
                            with v.VCol(cols=6):
                                with v.VRow(dense=True, no_gutters=True):
                                    v.VTextField(
                                        v_model=(f"f_{c}_lo",),
                                        label=f"{c} [{unit}] ≥" if unit else f"{c} ≥",
                                        id=f"f_{c}_lo",
                                        **dense,
                                    )
                                    v.VTextField(
                                        v_model=(f"f_{c}_hi",), label="≤", id=f"f_{c}_hi", **dense, classes="ml-1"
                                    )
                    v.VTextField(
                        v_model=("f_other",),
                        label="more ranges: NAME lo:hi; ... (e.g. TK_T1T12 30:50; DH_L4-L5 8:)",
                        id="f_other",
                        classes="mt-2",
                        **dense,
                    )
                    with v.VRow(dense=True, classes="mt-1"):
                        with v.VCol(cols=6):
                            v.VSelect(
                                v_model=("f_gap",), items=("gap_choices",), label="GAP category", multiple=True, **dense
                            )
                        with v.VCol(cols=6):
                            v.VSelect(v_model=("f_kind",), items=("kind_choices",), label="models", **dense)
                        for f in self.data.flags:
                            with v.VCol(cols=6):
                                v.VSelect(v_model=(f"f_{f}",), items=("flag_choices",), label=f, **dense)
                    html.Div(
                        "{{ n_match }} of {{ n_total }} models match ({{ filter_ms }} ms)",
                        id="match-count",
                        classes="text-body-2 my-2",
                    )
                    html.Div(v_html=("hist_svg",), id="histograms")
                    v.VDivider(classes="my-2")
                    html.Div("Find my patient (deg; any subset, PI = PT + SS)", classes="text-subtitle-2")
                    with v.VRow(dense=True):
                        for k in ("PI", "PT", "SS", "LL"):
                            with v.VCol(cols=3):
                                v.VTextField(v_model=(f"pat_{k}",), label=k, id=f"pat_{k}", **dense)
                    v.VBtn("find", click=self.find_patient, id="find", size="small", classes="mt-2")
                    html.Div(
                        "distance d = RMS over the given parameters of (model - target) / cohort SD",
                        classes="text-caption",
                    )
                    with html.Table(classes="text-caption", v_show="nearest.length"):
                        with html.Tr(v_for="r in nearest", key="r.model_id"):
                            with html.Td():
                                v.VBtn(
                                    "{{ r.model_id }}",
                                    variant="text",
                                    size="x-small",
                                    click=(self.select, "[r.model_id]"),
                                )
                            html.Td("d = {{ r.distance }}")
                            html.Td("PI {{ r.PI }} PT {{ r.PT }} SS {{ r.SS }} LL {{ r.LL }}")
                    html.Div("{{ fit_text }}", classes="text-caption", id="fit-text")
                    with html.Div(v_show="fit_weights.length"):
                        v.VBtn("show continuous model", click=self.show_fit, size="x-small", id="show-fit")
                        v.VBtn(
                            "its .inp",
                            size="x-small",
                            classes="ml-1",
                            id="dl-fit",
                            click="utils.download('personalized.inp', trigger('download_fit', []), 'text/plain')",
                        )
            with layout.content:
                with v.VContainer(fluid=True, classes="pa-2"):
                    v.VAlert(
                        "{{ message }}",
                        v_show="message",
                        type=("message_kind",),
                        density="compact",
                        closable=True,
                        click_close="message = ''",
                        id="message",
                    )
                    v.VAlert(
                        "Not in this folder: {{ missing.join('; ') }}",
                        v_show="missing.length",
                        type="info",
                        density="compact",
                        id="missing",
                    )
                    with v.VRow(dense=True):
                        with v.VCol(cols=8):
                            with v.VRow(dense=True, align="center"):
                                v.VTextField(
                                    v_model=("model_input",),
                                    label="model ID (model_NNNNN or patient ID)",
                                    id="model_input",
                                    __events=["keyup"],
                                    keyup_enter=(self.select, "[model_input]"),
                                    **dense,
                                )
                                v.VBtn("show", click=(self.select, "[model_input]"), id="show", classes="ml-2")
                                v.VTextField(
                                    v_model=("overlay_input",),
                                    label="compare with (ID)",
                                    classes="ml-4",
                                    id="overlay_input",
                                    **dense,
                                )
                                v.VBtn("overlay", click=(self.set_overlay, "['id']"), size="small", classes="ml-1")
                                v.VBtn("mean", click=(self.set_overlay, "['mean']"), size="small", classes="ml-1")
                                v.VBtn("clear", click=(self.set_overlay, "['none']"), size="small", classes="ml-1")
                            html.Div("{{ shown }} {{ overlay_label }}", classes="text-caption", id="shown")
                            with html.Div(style="height: 480px; border: 1px solid #ddd", id="view-box"):
                                view = self.view = vtk_widgets.VtkLocalView(self.scene.window, ref="view")
                                self.ctrl.view_update = view.update
                                self.ctrl.view_reset_camera = view.reset_camera
                            with v.VRow(dense=True, classes="mt-1"):
                                for i in range(self.n_sliders):
                                    with v.VCol():
                                        v.VSlider(
                                            v_model=(f"w_{i}",),
                                            min=("-slider_lim",),
                                            max=("slider_lim",),
                                            step=0.05,
                                            label=f"w{i + 1}",
                                            thumb_label=True,
                                            hide_details=True,
                                            density="compact",
                                            id=f"slider_{i}",
                                        )
                            html.Div(
                                "mode weights in SD; the sliders reshape the model live by the hex SSM's linear "
                                "formula ({{ live_ms }} ms on the server)",
                                classes="text-caption",
                            )
                        with v.VCol(cols=4):
                            html.Div("{{ selected_id || 'no model selected' }}", classes="text-subtitle-2")
                            with html.Table(classes="text-body-2", id="params"):
                                with html.Tr(v_for="p in params", key="p.name"):
                                    html.Td("{{ p.name }}")
                                    html.Td("{{ p.value }}", id=("'param-' + p.name",))
                                    html.Td("{{ p.unit }}")
                            v.VDivider(classes="my-2")
                            html.Div("Download", classes="text-subtitle-2")
                            for fmt, mime in (
                                ("inp", "text/plain"),
                                ("stl", "application/octet-stream"),
                                ("vtu", "application/xml"),
                            ):
                                v.VBtn(
                                    f".{fmt}",
                                    size="small",
                                    classes="mr-1 mb-1",
                                    disabled=("!selected_id",),
                                    id=f"dl-{fmt}",
                                    click=f"utils.download(`${{selected_id}}.{fmt}`, trigger('download_model', [selected_id, '{fmt}']), '{mime}')",
                                )
                            html.Br()
                            v.VBtn(
                                "table .csv",
                                size="small",
                                classes="mr-1 mb-1",
                                id="dl-csv",
                                click="utils.download('virtual_cohort_selection.csv', trigger('download_table', ['csv']), 'text/csv')",
                            )
                            v.VBtn(
                                "table .xlsx",
                                size="small",
                                classes="mr-1 mb-1",
                                id="dl-xlsx",
                                click="utils.download('virtual_cohort_selection.xlsx', trigger('download_table', ['xlsx']), "
                                "'application/vnd.openxmlformats-officedocument.spreadsheetml.sheet')",
                            )
                            v.VBtn(
                                "decks of the selection (.zip, at most {{ max_zip }})",
                                size="small",
                                classes="mb-1",
                                id="dl-zip",
                                disabled=("zip_busy || n_match > max_zip",),
                                click="utils.download('spinecohort_decks.zip', trigger('download_zip', []), 'application/zip')",
                            )
                            v.VProgressLinear(
                                model_value=("zip_progress",), v_show="zip_busy", height=6, id="zip-progress"
                            )
                    with v.VDataTableServer(
                        headers=("headers",),
                        items=("rows",),
                        items_length=("n_match",),
                        page=("page",),
                        items_per_page=("per_page",),
                        sort_by=("sort_by",),
                        update_options=(self.on_options, "[$event]"),
                        density="compact",
                        id="table",
                        classes="mt-2",
                    ):
                        with v.Template(raw_attrs=['v-slot:item.model_id="{ item }"']):
                            v.VBtn(
                                "{{ item.model_id }}",
                                variant="text",
                                size="small",
                                click=(self.select, "[item.model_id]"),
                                classes="model-link",
                                style="text-transform: none",
                            )
        self.layout = layout


def serve(data: CohortData, host: str = "127.0.0.1", port: int = 8080, max_zip: int = MAX_ZIP_MODELS) -> None:
    """Start the platform (blocking) on host:port; no timer stops it when the last browser leaves."""
    from trame.app import get_server

    argv, sys.argv = sys.argv, sys.argv[:1]  # trame reads its own options from sys.argv: ours are not for it
    try:
        server = get_server("spinecohort", client_type="vue3")
        Platform(data, server, max_zip=max_zip)
        server.start(host=host, port=port, open_browser=False, timeout=0, show_connection_info=False)
    finally:
        sys.argv = argv
