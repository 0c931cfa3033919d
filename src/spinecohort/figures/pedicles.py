"""Figure of the hex pedicles on the labeled reference: per vertebra a view from above and from the left of the
body's hexes, the arch's skin and the two pedicle blocks, with the labeled pedicle roots they are fitted to.

``python -m spinecohort.figures.pedicles OUT.png [--levels T6 T12 L3]`` renders off-screen (pyvista); the
template is the coarse one on the reference (`tests/conftest.py`'s ``real_template``), so the figure needs no
pipeline run.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import pyvista as pv

from spinecohort.fe.connections import body_layer
from spinecohort.fe.pedicles import SIDES, pedicle_blocks
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, HexTemplate, build_template


def reference_template() -> HexTemplate:
    """The coarse hex template on the labeled reference, its pedicle roots and facet surfaces carried."""
    from spinecohort.anatomy.reference import load_reference
    from spinecohort.cohort.real import first_use_reference

    ref = first_use_reference(load_reference())
    res = replace(TEMPLATE_RESOLUTIONS["coarse"], cep_diameter_fraction=0.7)
    return build_template(ref.vertices, ref.faces, ref.landmarks, res)


def _hex_grid(points: np.ndarray, hexes: np.ndarray) -> pv.UnstructuredGrid:
    cells = np.hstack([np.full((len(hexes), 1), 8), hexes]).ravel()
    return pv.UnstructuredGrid(cells, np.full(len(hexes), pv.CellType.HEXAHEDRON), points)


def render(template: HexTemplate, out_png: str, levels=("T6", "T12", "L3"), window=(1800, 1200)) -> None:
    """One row per level: from above (anterior up) and from the left (anterior right)."""
    p = pedicle_blocks(template, template.nodes)
    every = np.concatenate([template.nodes, p.points])
    nq = len(template.grid.quads)
    pl = pv.Plotter(shape=(2, len(levels)), window_size=window, off_screen=True, border=False)
    for col, lv in enumerate(levels):
        lo, hi = body_layer(template, lv, 0.0), body_layer(template, lv, 1.0)
        body = _hex_grid(template.nodes, template.hexes[lo * nq : hi * nq])
        tris = template.tris[template.elsets[f"POST_{lv}"]]
        arch = pv.PolyData(template.nodes, np.hstack([np.full((len(tris), 1), 3), tris]).ravel()).clean()
        ped = _hex_grid(every, np.concatenate([p.hexes[p.elsets[f"PED_{lv}_{s[0].upper()}"]] for s in SIDES]))
        roots = np.concatenate([template.sites[f"pedicle_{s}/{lv}"] for s in SIDES])
        b = np.array(arch.bounds)
        centre = 0.5 * (b[::2] + b[1::2])
        for row, (view, label) in enumerate((("view_xy", "from above"), ("view_yz", "from the left"))):
            pl.subplot(row, col)
            pl.add_mesh(body, color="wheat", show_edges=True, opacity=0.6)
            pl.add_mesh(arch, color="lightsteelblue", opacity=0.35)
            pl.add_mesh(ped, color="firebrick", show_edges=True)
            pl.add_points(template.nodes[roots], color="darkgreen", point_size=6, render_points_as_spheres=True)
            getattr(pl, view)(negative=view == "view_yz")
            pl.set_focus(centre)
            pl.camera.parallel_projection = True
            pl.camera.parallel_scale = 0.6 * float(max(b[1::2] - b[::2]))
            pl.add_text(f"{lv} {label}", font_size=11, color="black")
    pl.set_background("white")
    pl.screenshot(out_png)
    pl.close()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="PNG file to write")
    ap.add_argument("--levels", nargs="+", default=["T6", "T12", "L3"])
    args = ap.parse_args(argv)
    render(reference_template(), args.out, tuple(args.levels))


if __name__ == "__main__":
    main()
