"""The layout of the platform's page (Vuetify 3 through trame): what a user sees and clicks.

Left drawer: *find my patient* first (the question most users come with), then the filters with full
parameter names, units and a hover explanation, the match count and the histograms.  Main area: the
model field, the 3D view with its orientation marker and the mode sliders, the panel of the shape on
screen (parameters, tissue legend, downloads), then the table.  Every hover text is a ``title``
attribute: the browser's own tooltip, no script.
"""

from __future__ import annotations

from spinecohort.web.labels import explain, label, label_with_unit
from spinecohort.web.scene import legend_entries

#: the 3D view's height: most of a laptop screen, leaving a large screen room for the table under it
VIEW_HEIGHT = "max(420px, calc(100vh - 520px))"
MIME = {
    "inp": "text/plain",
    "stl": "application/octet-stream",
    "vtu": "application/xml",
    "csv": "text/csv",
    "xlsx": "application/vnd.openxmlformats-officedocument.spreadsheetml.sheet",
    "zip": "application/zip",
}
#: the four parameters of "find my patient": (state key, label)
PATIENT_FIELDS = (("PI", "PI"), ("PT", "PT"), ("SS", "SS"), ("LL", "LL"))


def download_js(trigger: str, args: str, filename: str, mime: str) -> str:
    """A click that asks the server for bytes and saves them only if it sent some: a refused request
    answers nothing (its reason is in the page's message), so no empty file is saved."""
    return f"trigger('{trigger}', {args}).then((b) => b && utils.download({filename}, b, '{mime}'))"


def build_page(p):
    """The page of Platform ``p`` (its state names are the ``v_model`` and the texts below)."""
    from trame.ui.vuetify3 import SinglePageWithDrawerLayout
    from trame.widgets import html
    from trame.widgets import vtk as vtk_widgets
    from trame.widgets import vuetify3 as v

    dense = {"density": "compact", "hide_details": True, "variant": "outlined"}
    with SinglePageWithDrawerLayout(p.server, width=450) as layout:
        layout.title.set_text("spinecohort platform")
        layout.footer.hide()  # the framework's credit line would cover the table's last rows
        with layout.toolbar:
            v.VSpacer()
            html.Div(
                "{{ n_match.toLocaleString() }} of {{ n_total.toLocaleString() }} models match",
                classes="text-subtitle-1 font-weight-medium mr-6",
                id="match-count-top",
            )
            html.Div("{{ title }}", classes="text-caption mr-4", id="data-title")
        with layout.drawer:
            with v.VContainer(classes="pa-2"):
                # ---------------------------------------------------------------- find my patient
                html.Div("Find my patient", classes="text-subtitle-1 font-weight-medium")
                html.Div(
                    "Give any of the patient's angles (deg); two of PI, PT, SS give the third (PI = PT + SS).",
                    classes="text-caption",
                )
                with v.VRow(dense=True, classes="mt-1"):
                    for k, short in PATIENT_FIELDS:
                        with v.VCol(cols=3):
                            v.VTextField(
                                v_model=(f"pat_{k}",),
                                label=f"{short} (°)",
                                id=f"pat_{k}",
                                title=f"{label(k)}: {explain(k)}",
                                **dense,
                            )
                with v.VRow(dense=True, align="center", classes="mt-1"):
                    v.VBtn("find nearest models", click=p.find_patient, id="find", size="small", color="primary")
                    html.Span(
                        "nearest by d = RMS of (model − patient) / cohort SD",
                        classes="text-caption ml-2",
                        title="d = 1 means one cohort standard deviation away per given parameter, on average",
                    )
                with html.Table(classes="text-caption mt-1", v_show="nearest.length", id="nearest"):
                    with html.Tr(v_for="r in nearest", key="r.model_id"):
                        with html.Td():
                            v.VBtn(
                                "{{ r.model_id }}",
                                variant="tonal",
                                size="x-small",
                                click=(p.select, "[r.model_id]"),
                                style="text-transform: none",
                            )
                        html.Td("d = {{ r.distance }}", classes="px-1")
                        html.Td("{{ r.values }}")
                html.Div("{{ fit_text }}", classes="text-caption", id="fit-text")
                with html.Div(v_show="fit_weights.length"):
                    v.VBtn("show continuous model", click=p.show_fit, size="x-small", id="show-fit")
                    v.VBtn(
                        "its .inp deck",
                        size="x-small",
                        classes="ml-1",
                        id="dl-fit",
                        click=download_js("download_fit", "[]", "'personalized.inp'", MIME["inp"]),
                    )
                v.VDivider(classes="my-2")
                # ---------------------------------------------------------------- filters
                html.Div("Filter the cohort (bounds inclusive)", classes="text-subtitle-1 font-weight-medium")
                for c in p.ranges:
                    with v.VRow(dense=True, align="center", classes="my-0"):
                        with v.VCol(cols=6, classes="py-0"):
                            html.Div(label_with_unit(c), title=explain(c), classes="text-body-2 filter-label")
                        with v.VCol(cols=3, classes="py-0"):
                            v.VTextField(v_model=(f"f_{c}_lo",), placeholder="min", id=f"f_{c}_lo", **dense)
                        with v.VCol(cols=3, classes="py-0"):
                            v.VTextField(v_model=(f"f_{c}_hi",), placeholder="max", id=f"f_{c}_hi", **dense)
                v.VTextField(
                    v_model=("f_other",),
                    label="more ranges: NAME lo:hi; …",
                    placeholder="e.g. TK_T1T12 30:50; DH_L4-L5 8:",
                    title="any numeric column of the downloaded table, in the grammar of `spinecohort query`",
                    id="f_other",
                    classes="mt-2",
                    **dense,
                )
                with v.VRow(dense=True, classes="mt-1"):
                    if "GAP_category" in p.columns:
                        with v.VCol(cols=12):
                            v.VSelect(
                                v_model=("f_gap",),
                                items=("gap_choices",),
                                label="GAP category",
                                multiple=True,
                                chips=True,
                                title=explain("GAP_category"),
                                id="f_gap",
                                **dense,
                            )
                    with v.VCol(cols=6):
                        v.VSelect(v_model=("f_kind",), items=("kind_choices",), label="models", id="f_kind", **dense)
                    for f in p.data.flags:
                        with v.VCol(cols=3):
                            v.VSelect(v_model=(f"f_{f}",), items=("flag_choices",), label=f, title=explain(f), **dense)
                html.Div(
                    "{{ n_match }} of {{ n_total }} models match ({{ filter_ms }} ms)",
                    id="match-count",
                    classes="text-body-1 font-weight-medium my-2",
                )
                html.Div(v_html=("hist_svg",), id="histograms")
                html.Div("grey: the whole cohort; blue: the models that match", classes="text-caption")
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
                with v.VRow(dense=True, align="center"):
                    with v.VCol(cols=4):
                        v.VTextField(
                            v_model=("model_input",),
                            label="model ID (model_NNNNN or a patient ID), Enter shows it",
                            id="model_input",
                            __events=[("keyup_enter", "keyup.enter")],
                            keyup_enter=(p.select, "[model_input]"),
                            **dense,
                        )
                    v.VBtn("show", click=(p.select, "[model_input]"), id="show", color="primary")
                    with v.VCol(cols=3, classes="ml-4"):
                        v.VTextField(v_model=("overlay_input",), label="compare with (ID)", id="overlay_input", **dense)
                    v.VBtn("overlay", click=(p.set_overlay, "['id']"), size="small", classes="ml-1")
                    v.VBtn("mean", click=(p.set_overlay, "['mean']"), size="small", classes="ml-1", id="overlay-mean")
                    v.VBtn("clear", click=(p.set_overlay, "['none']"), size="small", classes="ml-1")
                with v.VRow(dense=True):
                    with v.VCol(cols=7):
                        html.Div("{{ shown }} {{ overlay_label }}", classes="text-body-2", id="shown")
                        with html.Div(style=f"height: {VIEW_HEIGHT}; border: 1px solid #ddd; display: flex"):
                            _legend(html)
                            with html.Div(style="flex: 1; position: relative", id="view-box"):
                                view = p.view = vtk_widgets.VtkLocalView(p.scene.window, ref="view")
                                p.ctrl.view_update = view.update
                                p.ctrl.view_reset_camera = view.reset_camera
                        with v.VRow(dense=True, classes="mt-1", id="sliders"):
                            for i in range(p.n_sliders):
                                with v.VCol(classes="py-0", title=explain("w1")):
                                    html.Div(
                                        f"shape mode {i + 1}: {{{{ Number(w_{i}).toFixed(2) }}}} SD",
                                        classes="text-caption",
                                    )
                                    v.VSlider(
                                        v_model=(f"w_{i}",),
                                        min=("-slider_lim",),
                                        max=("slider_lim",),
                                        step=0.05,
                                        hide_details=True,
                                        density="compact",
                                        id=f"slider_{i}",
                                    )
                        html.Div(
                            "the sliders reshape the model live by the hex SSM's linear formula"
                            "{{ shown_kind === 'live' ? ' (' + live_ms + ' ms on the server)' : '' }}; "
                            "a live shape's .inp has the mesh checks of a stored model",
                            classes="text-caption",
                        )
                    with v.VCol(cols=5, style=f"max-height: calc({VIEW_HEIGHT} + 130px); overflow-y: auto"):
                        _panel(p, html, v)
                with v.VDataTableServer(
                    headers=("headers",),
                    items=("rows",),
                    items_length=("n_match",),
                    page=("page",),
                    items_per_page=("per_page",),
                    items_per_page_options=("page_sizes",),
                    sort_by=("sort_by",),
                    update_options=(p.on_options, "[$event]"),
                    density="compact",
                    fixed_header=True,
                    height="calc(100vh - 180px)",
                    id="table",
                    classes="mt-2",
                    hover=True,
                ):
                    with v.Template(raw_attrs=['v-slot:headers="{ columns, toggleSort, isSorted, getSortIcon }"']):
                        with html.Tr():
                            with html.Th(
                                v_for="(c, i) in columns",
                                key="c.key",
                                title=("headers[i].hover",),
                                click="c.sortable && toggleSort(c)",
                                classes="text-caption font-weight-bold",
                                style="position: sticky; top: 0; background: #f5f5f5; z-index: 2; cursor: pointer; "
                                "white-space: normal; line-height: 1.2; min-width: 70px",
                            ):
                                html.Span("{{ c.title }}")
                                v.VIcon(v_if="isSorted(c)", icon=("getSortIcon(c)",), size="x-small")
                    with v.Template(raw_attrs=['v-slot:item.GAP_category="{ item }"']):
                        html.Span("{{ item.GAP_category }}", style="white-space: nowrap")
                    with v.Template(raw_attrs=['v-slot:item.weights="{ item }"']):
                        html.Span("{{ item.weights }}", style="white-space: nowrap; font-family: monospace")
                    with v.Template(raw_attrs=['v-slot:item.model_id="{ item }"']):
                        v.VBtn(
                            "{{ item.model_id }}",
                            variant="text",
                            size="small",
                            click=(p.select, "[item.model_id]"),
                            classes="model-link",
                            style="text-transform: none",
                        )
    return layout


def _panel(p, html, v) -> None:
    """The shape on screen: its parameters, the tissue legend, its downloads and the table's."""
    html.Div(
        "{{ shown_key.startsWith('live') ? 'live shape' : (shown_key || 'the mean model') }}",
        classes="text-subtitle-1 font-weight-medium",
        id="shown-title",
    )
    with html.Table(classes="text-body-2", id="params", style="width: 100%"):
        with html.Tr(v_for="q in params", key="q.key", title=("q.hover",)):
            html.Td("{{ q.name }}")
            html.Td("{{ q.value }}", id=("'param-' + q.key",), classes="text-right px-1")
            html.Td("{{ q.unit }}")
    html.Div(
        "parameters are measured on the stored models; a live shape has none until it is stored",
        v_show="shown_kind === 'live'",
        classes="text-caption",
        id="live-note",
    )
    v.VDivider(classes="my-2")
    html.Div("Download the shape on screen", classes="text-subtitle-2")
    for fmt in ("inp", "stl", "vtu"):
        v.VBtn(
            f".{fmt}",
            size="small",
            classes="mr-1 mb-1",
            disabled=(f"!dl_formats.includes('{fmt}')",),
            id=f"dl-{fmt}",
            title={"inp": "CalculiX / Abaqus deck", "stl": "triangulated surface", "vtu": "hex mesh for ParaView"}[fmt],
            click=download_js("download_shown", f"[shown_key, '{fmt}']", f"`${{shown_file}}.{fmt}`", MIME[fmt]),
        )
    html.Div("Download the table", classes="text-subtitle-2 mt-1")
    wb_title = "the run's Descriptive_List.xlsx (prepared by the pipeline: every model, the patients, notes)"
    for text, ident, args, name, mime, extra in (
        ("selection .csv", "dl-csv", "['csv']", "virtual_cohort_selection.csv", "csv", {}),
        ("selection .xlsx", "dl-xlsx", "['xlsx']", "virtual_cohort_selection.xlsx", "xlsx", {}),
        (
            "whole cohort .xlsx",
            "dl-workbook",
            "['workbook']",
            "Descriptive_List.xlsx",
            "xlsx",
            {"v_show": "has_workbook", "title": wb_title},
        ),
        (
            "decks of the selection (.zip, at most {{ max_zip }})",
            "dl-zip",
            "[]",
            "spinecohort_decks.zip",
            "zip",
            {"disabled": ("zip_busy || n_match > max_zip",)},
        ),
    ):
        trigger = "download_zip" if mime == "zip" else "download_table"
        v.VBtn(
            text,
            size="small",
            classes="mr-1 mb-1",
            id=ident,
            click=download_js(trigger, args, f"'{name}'", MIME[mime]),
            **extra,
        )
    v.VProgressLinear(model_value=("zip_progress",), v_show="zip_busy", height=8, id="zip-progress", color="primary")
    html.Div("{{ zip_text }}", v_show="zip_busy", classes="text-caption", id="zip-text")


def _legend(html) -> None:
    """The tissue colours of the view, in a strip at its left (outside the canvas)."""
    with html.Div(
        id="legend",
        classes="pa-1",
        style="width: 150px; overflow-y: auto; font-size: 11px; line-height: 1.25; border-right: 1px solid #eee",
    ):
        html.Div("Tissues", classes="font-weight-bold mb-1")
        for e in legend_entries():
            with html.Div(classes="mb-1", style="display: flex; align-items: flex-start"):
                html.Span(
                    style=f"flex: none; width: 10px; height: 10px; margin: 2px 4px 0 0; background: {e['colour']}; "
                    "border: 1px solid #999"
                )
                html.Span(e["name"])
        html.Div(
            "Arrows: R right, A anterior, S superior. Drag to turn the model, wheel to zoom.",
            classes="mt-2",
            id="orientation-note",
        )
