"""The moment the fixation of every solved ROM deck under OUT carries (docs/moment_check.md).

    .venv/bin/python scripts/moment_check.py OUT [OUT ...]

For every ``rom_*.inp`` with its ``.dat`` under OUT (`scripts/rom_explore.py` writes them): the ROT NODE's
*CLOAD, the moment the fixed nodes carry at the last printed load (minus sum (x - p) x RF, `spinecohort.rom.
reaction`), its magnitude and its component along the load case's moment (the first solve's *CLOAD: a deck
``<job>_m<i>.inp`` is moment iteration i of ``<job>.inp``), the net reaction force, the ROT NODE's rotation
vector and the moment `physical_moment` predicts from the *CLOAD and that rotation.  N.mm, N, degrees.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, nargs="+")
    args = ap.parse_args(argv)

    from spinecohort.fe.calculix import parse_dat
    from spinecohort.rom.reaction import deck_nodes_and_loads, physical_moment, reactions

    np.set_printoptions(precision=1, suppress=True, floatmode="fixed")
    targets: dict[Path, np.ndarray] = {}
    for out in args.out:
        for inp in sorted(out.rglob("rom_*.inp"), key=lambda p: (p.parent, len(p.stem), p.stem)):
            dat = inp.with_suffix(".dat")
            if not dat.exists():
                continue
            nodes, cloads = deck_nodes_and_loads(inp.read_text())
            q = np.zeros(3)
            for _, dof, value in cloads:
                q[dof - 1] += value
            base = inp.with_name(re.sub(r"_m\d+$", "", inp.stem) + ".inp")
            target = targets.setdefault(base, q) if base == inp else targets.get(base, q)
            prints = parse_dat(dat.read_text())
            rf = reactions(nodes, prints)
            rot = [b for b in prints if b.node_set.upper() == "ROTTOP"]
            if not rf or not rot:
                print(f"{inp}: no RF / ROTTOP prints")
                continue
            r, theta = rf[-1], rot[-1].values[0]
            carried = r.carried_nmm()
            axis = target / np.linalg.norm(target)
            print(
                f"{inp.relative_to(out)} (load {r.time:.4f}): *CLOAD {q}  carried {carried} |M| "
                f"{np.linalg.norm(carried):.1f} along the load case's axis {carried @ axis:.1f} of "
                f"{np.linalg.norm(target) * r.time:.1f}; off-axis {np.linalg.norm(carried - (carried @ axis) * axis):.1f}"
                f"; net force {r.force_n} N (|F| {np.linalg.norm(r.force_n):.2e}); top rotation "
                f"{np.degrees(theta)} deg (|{np.degrees(np.linalg.norm(theta)):.2f}|); T^-T Q "
                f"{physical_moment(q * r.time, theta)}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
