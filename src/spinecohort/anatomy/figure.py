"""Figure of the labeled reference spine: regions, endplate rims, femoral-head caps, ligament sites.

``python -m spinecohort.anatomy.figure OUT.png [--reference FILE]`` renders off-screen (pyvista).
"""

from __future__ import annotations

import argparse

import numpy as np
import pyvista as pv

from spinecohort.anatomy.labels import REGIONS
from spinecohort.anatomy.reference import Reference, load_reference
from spinecohort.anatomy.surface import to_polydata

#: one colour per region (REGIONS order); left/right pairs share a hue, darker on the right
REGION_COLOURS = (
    "#e8dcc0",  # body
    "#4e9a06",
    "#2e5e04",  # pedicles
    "#3465a4",  # lamina
    "#75507b",  # spinous
    "#f57900",
    "#a85300",  # transverse
    "#cc0000",
    "#8a0000",  # superior facets
    "#06989a",
    "#045f60",  # inferior facets
    "#babdb6",  # sacrum
    "#edd400",  # S1 plate
    "#d3c7a0",  # ilium
    "#c4a000",  # pubis
    "#729fcf",  # femoral head
)

_SITE_COLOURS = {"ALL": "#ff00ff", "PLL": "#00ffff", "SSL": "#000000", "ISL": "#555555", "ITL": "#ffffff"}


def _sub(ref: Reference, keep: np.ndarray) -> tuple[pv.PolyData, np.ndarray]:
    faces = ref.faces[np.all(keep[ref.faces], axis=1)]
    used = np.unique(faces)
    remap = np.full(len(ref.vertices), -1)
    remap[used] = np.arange(len(used))
    mesh = to_polydata(ref.vertices[used], remap[faces])
    mesh["region"] = ref.region[used]
    return mesh, used


def render(ref: Reference, out_png: str, window=(2400, 1500)) -> None:
    """Four panels: whole model from the left and the front, L3-L5 and T6-T8 close up, with the endplate rims
    (yellow), femoral-head caps (blue points) and ligament sites (ALL magenta, PLL cyan, SSL/ISL grey)."""
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(REGION_COLOURS)
    clim = (-0.5, len(REGIONS) - 0.5)
    pl = pv.Plotter(shape=(2, 3), window_size=window, off_screen=True, border=False)
    panels = [
        ((0, 0), np.ones(len(ref.vertices), bool), "yz", "reference, from the left"),
        ((1, 0), np.ones(len(ref.vertices), bool), "xz", "from the front"),
        ((0, 1), np.isin(ref.level, [14, 15, 16]), "yz", "L3-L5 from the left"),
        ((1, 1), np.isin(ref.level, [14, 15, 16]), "-xy", "L3-L5 from below-behind"),
        ((0, 2), np.isin(ref.level, [5, 6, 7]), "yz", "T6-T8 from the left"),
        ((1, 2), np.isin(ref.level, [5, 6, 7]), "xy", "T6-T8 from above"),
    ]
    lm = ref.landmarks
    for (r, c), keep, view, title in panels:
        pl.subplot(r, c)
        mesh, used = _sub(ref, keep)
        pl.add_mesh(mesh, scalars="region", cmap=cmap, clim=clim, show_scalar_bar=False, smooth_shading=True)
        marks = [(np.concatenate(list(lm.rim_sup.values()) + list(lm.rim_inf.values())), "#fce94f", 4)]
        marks.append((np.concatenate(list(lm.femoral_head.values())), "#204a87", 3))
        for key, colour in _SITE_COLOURS.items():
            idx = [v for name, per in ref.sets.items() if name.startswith(f"site_{key}") for v in per.values()]
            if idx:
                marks.append((np.concatenate(idx), colour, 6))
        for idx, colour, size in marks:
            idx = idx[keep[idx]]
            if len(idx):
                pl.add_points(ref.vertices[idx], color=colour, point_size=size, render_points_as_spheres=True)
        if view == "-xy":
            pl.view_xy(negative=True)
            pl.camera.elevation = -30
        else:
            getattr(pl, f"view_{view}")()
        pl.add_text(title, font_size=10, color="black")
        del used
    pl.subplot(0, 0)
    legend = [[name, REGION_COLOURS[i]] for i, name in enumerate(REGIONS)]
    pl.add_legend(legend, bcolor="white", size=(0.35, 0.55), loc="lower left")
    pl.set_background("white")
    pl.screenshot(out_png)
    pl.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Render the labeled reference spine")
    ap.add_argument("out_png")
    ap.add_argument("--reference", default=None, help="reference npz (default: the vendored one)")
    args = ap.parse_args(argv)
    render(load_reference(args.reference), args.out_png)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
