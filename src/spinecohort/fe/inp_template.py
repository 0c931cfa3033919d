"""Template decks: the seed's "replace the point coordinates in Mean_Model (Template).inp" step, and reading
decks back.

`substitute_coordinates` is written here rather than borrowed: everything but the *NODE data lines must stay
byte-identical, which no mesh library guarantees.  `read_inp` reads a whole deck with meshio.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spinecohort.atomic import write_text_atomic
from spinecohort.fe.writers import format_node_lines

_NODE_KEYWORD = re.compile(r"^\*NODE\s*(,[^\n]*)?$", re.IGNORECASE | re.MULTILINE)
_NEXT_KEYWORD = re.compile(r"^\*(?!\*)", re.MULTILINE)


@dataclass(frozen=True)
class InpTemplate:
    """A deck split around its *NODE data lines: head (up to and including the *NODE keyword line),
    node ids in file order, tail (from the next keyword on)."""

    head: str
    node_ids: np.ndarray
    tail: str
    decimals: int


def _node_block_span(text: str) -> tuple[int, int]:
    """Character span of the data lines of the deck's only *NODE block."""
    heads = list(_NODE_KEYWORD.finditer(text))
    if not heads:
        raise ValueError("deck has no *NODE block")
    if len(heads) > 1:
        raise ValueError(f"deck has {len(heads)} *NODE blocks; exactly one is supported")
    data_start = heads[0].end() + 1
    nxt = _NEXT_KEYWORD.search(text, data_start)
    return data_start, (nxt.start() if nxt else len(text))


def _parse_node_block(block: str) -> np.ndarray:
    # comment lines inside the block would be lost by a substitution; refuse rather than drop them
    if "**" in block:
        raise ValueError("*NODE block contains comment lines; remove them first")
    values = np.array(block.replace(",", " ").split(), dtype=np.float64)
    if values.size == 0 or values.size % 4:
        raise ValueError("*NODE block must hold lines 'id, x, y, z' (3-D nodes)")
    return values.reshape(-1, 4)


def parse_template(template: str | Path, decimals: int | None = None) -> InpTemplate:
    """Split a deck (text, or path to a file) around its single *NODE block.

    decimals: precision for substituted coordinates; default = that of the template's first node line.
    """
    text = _read_text(template)
    data_start, data_end = _node_block_span(text)
    block = text[data_start:data_end]
    table = _parse_node_block(block)
    if decimals is None:
        first = block.lstrip("\n").split("\n", 1)[0].split(",")[1].strip()
        decimals = len(first.partition(".")[2]) if ("." in first and "e" not in first.lower()) else 6
    return InpTemplate(text[:data_start], table[:, 0].astype(np.int64), text[data_end:], int(decimals))


def _read_text(template: str | Path) -> str:
    if isinstance(template, Path) or ("\n" not in template and len(template) < 4096):
        path = Path(template)
        if not path.is_file():
            raise ValueError(f"template deck {path} does not exist")
        return path.read_text()
    return template


def substitute_coordinates(
    template: str | Path | InpTemplate, points_mm: np.ndarray, out_path: str | Path | None = None
) -> str:
    """A model's deck = the template deck with only its *NODE data lines replaced by `points_mm`.

    points_mm: (N, 3) coordinates in mm, in the template's node order.  Node ids, elements, sets,
    materials and every other byte of the template stay identical.  Returns the text; writes it to
    `out_path` when given.  Pass a parsed `InpTemplate` when substituting many models.
    """
    tpl = template if isinstance(template, InpTemplate) else parse_template(template)
    points_mm = np.asarray(points_mm, dtype=np.float64)
    if points_mm.shape != (len(tpl.node_ids), 3):
        raise ValueError(
            f"points must have shape ({len(tpl.node_ids)}, 3) to match the template's nodes, got {points_mm.shape}"
        )
    if not np.isfinite(points_mm).all():
        raise ValueError("points contain non-finite coordinates")
    text = tpl.head + format_node_lines(tpl.node_ids, points_mm, tpl.decimals) + tpl.tail
    if out_path is not None:
        write_text_atomic(out_path, text)
    return text


def read_inp_nodes(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Node ids (N,) int64 and coordinates (N, 3) mm of a deck's single *NODE block."""
    text = Path(path).read_text()
    data_start, data_end = _node_block_span(text)
    table = _parse_node_block(text[data_start:data_end])
    return table[:, 0].astype(np.int64), table[:, 1:]


def read_inp(path: str | Path):
    """meshio.Mesh of a deck, with SPRINGA and GAPUNI elements read as 'line' cells.

    meshio 5.3.5's Abaqus reader knows neither and raises on them; they are registered in meshio's type
    table (additive, idempotent entries) so ligaments, connectors and facet gaps read back as 2-node lines.
    """
    import meshio
    from meshio.abaqus import _abaqus

    for etype in ("SPRINGA", "GAPUNI"):
        _abaqus.abaqus_to_meshio_type.setdefault(etype, "line")
    return meshio.read(path, file_format="abaqus")
