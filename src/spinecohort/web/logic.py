"""Pure logic of the cohort platform over numpy arrays and tables: filters, nearest models, histograms, the
bounded zip, and the parsing of what a user types.  No I/O and no trame: unit-tested in isolation."""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Callable

import numpy as np
import pandas as pd

#: bounds of one zip of decks: models, and bytes of the archive (a request beyond them is refused)
MAX_ZIP_MODELS = 25
MAX_ZIP_BYTES = 1_000_000_000


class PlatformError(ValueError):
    """A request the platform refuses (bad ID, out-of-range value, inconsistent targets, missing data):
    its message is shown in the page and the server keeps serving."""


def filter_mask(
    table: pd.DataFrame,
    ranges: dict[str, tuple[float | None, float | None]] | None = None,
    categories: dict[str, list] | None = None,
    flags: dict[str, bool | None] | None = None,
) -> np.ndarray:
    """Rows of ``table`` that satisfy every filter: inclusive numeric ``ranges`` (column -> (lo, hi), None =
    open; NaN never matches; ``measure.tables.query_mask``, the test of ``spinecohort query``), ``categories`` (column -> allowed
    values; an empty list allows all) and boolean ``flags`` (column -> required value; None = either)."""
    from spinecohort.measure.tables import query_mask

    keep = np.ones(len(table), bool)
    ranges = {k: v for k, v in (ranges or {}).items() if v != (None, None)}
    if ranges:
        try:
            keep &= query_mask(table, ranges)
        except ValueError as exc:
            raise PlatformError(str(exc)) from None
    for col, allowed in (categories or {}).items():
        if allowed:
            keep &= table[col].isin(list(allowed)).to_numpy()
    for col, want in (flags or {}).items():
        if want is not None:
            keep &= table[col].fillna(False).astype(bool).to_numpy() == bool(want)
    return keep


def nearest_models(
    table: pd.DataFrame, targets: dict[str, float], k: int = 5, scale: dict[str, float] | None = None
) -> pd.DataFrame:
    """The ``k`` rows nearest to ``targets`` (parameter -> deg / mm) in the normalized distance

        d = sqrt( mean over the given parameters p of ((x_p - t_p) / s_p)^2 )

    with s_p the standard deviation of p over ``table`` (or ``scale``): d = 1 means one cohort SD away per
    parameter on average.  Returns those rows with a ``distance`` column (dimensionless), nearest first."""
    if not targets:
        raise PlatformError("give at least one of PI, PT, SS, LL")
    cols = list(targets)
    x = table[cols].to_numpy(float)
    t = np.array([targets[c] for c in cols], float)
    s = np.array([(scale or {}).get(c, np.nanstd(table[c].to_numpy(float))) for c in cols], float)
    s = np.where(s > 0, s, 1.0)  # a constant column (tiny test grids) counts in its own unit
    d = np.sqrt(np.mean(((x - t) / s) ** 2, axis=1))
    d = np.where(np.isfinite(d), d, np.inf)
    order = np.argsort(d, kind="stable")[:k]
    return table.iloc[order].assign(distance=d[order])


def histogram_counts(values: np.ndarray, selected: np.ndarray, bins: int = 24) -> dict:
    """Counts of all finite ``values`` and of the ``selected`` ones on shared edges (the selection drawn
    over the whole cohort): {edges (bins + 1,), all (bins,), selected (bins,)}."""
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    lo, hi = (v[ok].min(), v[ok].max()) if ok.any() else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    edges = np.linspace(lo, hi, bins + 1)
    return {
        "edges": edges,
        "all": np.histogram(v[ok], edges)[0],
        "selected": np.histogram(v[ok & np.asarray(selected, bool)], edges)[0],
    }


def bounded_zip(
    names: list[str],
    build: Callable[[str], bytes],
    max_models: int = MAX_ZIP_MODELS,
    max_bytes: int = MAX_ZIP_BYTES,
    progress: Callable[[int, int], None] | None = None,
) -> bytes:
    """A zip (deflated) of ``build(name)`` for each name, as ``<name>``; refused before any work when more
    than ``max_models`` names are asked, and stopped as soon as the archive would pass ``max_bytes``.
    ``progress(done, total)`` is called after each member."""
    if not names:
        raise PlatformError("no models to zip: select some rows first")
    if len(names) > max_models:
        raise PlatformError(f"{len(names)} models asked; a zip holds at most {max_models} (narrow the filter)")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as z:
        for i, name in enumerate(names):
            z.writestr(name, build(name))
            if buf.tell() > max_bytes:
                raise PlatformError(f"the zip passed {max_bytes / 1e6:.0f} MB after {i + 1} models; ask for fewer")
            if progress:
                progress(i + 1, len(names))
    return buf.getvalue()


def parse_bound(text, name: str) -> float | None:
    """A filter bound typed in the page: '' -> None (open), a number -> float, else PlatformError."""
    if text is None or str(text).strip() == "":
        return None
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise PlatformError(f"{name}: '{text}' is not a number") from None
    if not np.isfinite(v):
        raise PlatformError(f"{name}: '{text}' is not a finite number")
    return v


_XLSX_PARTS = {
    "[Content_Types].xml": '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>'
    '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
    '<Default Extension="rels" ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
    '<Default Extension="xml" ContentType="application/xml"/>'
    '<Override PartName="/xl/workbook.xml" '
    'ContentType="application/vnd.openxmlformats-officedocument.spreadsheetml.sheet.main+xml"/>'
    '<Override PartName="/xl/worksheets/sheet1.xml" '
    'ContentType="application/vnd.openxmlformats-officedocument.spreadsheetml.worksheet+xml"/></Types>',
    "_rels/.rels": '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>'
    '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
    '<Relationship Id="rId1" '
    'Type="http://schemas.openxmlformats.org/officeDocument/2006/relationships/officeDocument" '
    'Target="xl/workbook.xml"/></Relationships>',
    "xl/_rels/workbook.xml.rels": '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>'
    '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
    '<Relationship Id="rId1" '
    'Type="http://schemas.openxmlformats.org/officeDocument/2006/relationships/worksheet" '
    'Target="worksheets/sheet1.xml"/></Relationships>',
}


def _xlsx_cells(v: pd.Series, digits: int) -> np.ndarray:
    """One column as SpreadsheetML cells (an object array of strings): numbers as values (NaN an empty
    cell, which keeps the cells of the row in place), flags as booleans, the rest as inline text."""
    from xml.sax.saxutils import escape

    if v.dtype.kind == "b":
        return np.where(v.to_numpy(), '<c t="b"><v>1</v></c>', '<c t="b"><v>0</v></c>').astype(object)
    if v.dtype.kind in "iuf":
        x = np.round(v.to_numpy(float), digits)
        out = np.array(["<c><v>" + t + "</v></c>" for t in x.astype(str)], dtype=object)
        out[~np.isfinite(x)] = "<c/>"
        return out
    text = v.astype(object).where(v.notna(), "").astype(str)
    return np.array([f'<c t="inlineStr"><is><t>{escape(t)}</t></is></c>' if t else "<c/>" for t in text], object)


def xlsx_bytes(table: pd.DataFrame, sheet: str = "selection", digits: int = 4) -> bytes:
    """``table`` as an xlsx workbook of one sheet: a header row, then the values (floats rounded to
    ``digits``, NaN as empty cells, flags as booleans).  The SpreadsheetML is written column by column
    with numpy, which takes seconds for the 16,807 x 114 table where pandas' ``to_excel`` (openpyxl, one
    styled cell object each) takes most of a minute."""
    from xml.sax.saxutils import escape, quoteattr

    cols = [_xlsx_cells(pd.Series([str(c) for c in table.columns], dtype=object), digits)]
    body = [_xlsx_cells(table[c], digits) for c in table.columns]
    rows = ["<row>" + "".join(cols[0]) + "</row>"]
    rows += ["<row>" + "".join(r) + "</row>" for r in zip(*body)] if body else []
    sheet_xml = (
        '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>'
        '<worksheet xmlns="http://schemas.openxmlformats.org/spreadsheetml/2006/main"><sheetData>'
        + "".join(rows)
        + "</sheetData></worksheet>"
    )
    workbook = (
        '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>'
        '<workbook xmlns="http://schemas.openxmlformats.org/spreadsheetml/2006/main" '
        'xmlns:r="http://schemas.openxmlformats.org/officeDocument/2006/relationships">'
        f'<sheets><sheet name={quoteattr(escape(sheet[:31]))} sheetId="1" r:id="rId1"/></sheets></workbook>'
    )
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as z:
        for name, xml in (*_XLSX_PARTS.items(), ("xl/workbook.xml", workbook)):
            z.writestr(name, xml)
        z.writestr("xl/worksheets/sheet1.xml", sheet_xml)
    return buf.getvalue()


def histogram_svg(hists: dict[str, dict], titles: dict[str, str], width: int = 140, height: int = 56) -> str:
    """Small-multiple histograms as one inline SVG (scales to its container): per parameter the whole
    cohort (grey) and the current selection (blue) on the same count axis, so the selection shows as the
    part of the cohort it is; ``titles`` names each panel (default: the parameter)."""
    from html import escape

    cols = 3
    rows = math.ceil(len(hists) / cols) or 1
    cell_w, cell_h = width + 10, height + 30
    w_all, h_all = cols * cell_w, rows * cell_h
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {w_all} {h_all}" width="100%" '
        'font-family="sans-serif" font-size="10">'
    ]
    for k, (name, h) in enumerate(hists.items()):
        x0, y0 = (k % cols) * cell_w + 5, (k // cols) * cell_h + 12
        top = max(int(h["all"].max()), 1)
        n = len(h["all"])
        bw = width / n
        out.append(f'<text x="{x0}" y="{y0 - 2}">{escape(titles.get(name, name))}</text>')
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
