"""Nucleus element / material experiments on the ROM models (docs/moment_check.md "Session 10"), without
changing the package: patches the deck builder, then runs `rom_explore.py` with the remaining arguments.

    .venv/bin/python scripts/nucleus_element_explore.py VARIANT OUT [rom_explore args ...]

VARIANT: ``base`` (the config as is) | ``np_c3d8`` (nucleus in the bone's element block, i.e. C3D8; the
annulus stays C3D8R) | ``np_lin:E:nu`` (nucleus linear elastic, E MPa, Poisson ratio nu, element C3D8R).
Example (session 10): ``np_c3d8 /tmp/e/np_c3d8 --lumbar --cases lateral_left rom.threads=1``; read
``moment_carried_fraction`` in OUT/rom.csv."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import rom_explore  # noqa: E402

import spinecohort.fe.export as export  # noqa: E402
import spinecohort.rom.submodel as submodel  # noqa: E402
from spinecohort.fe.abaqus import LinearElastic  # noqa: E402


def patch(variant: str) -> None:
    if variant == "np_c3d8":
        export.DISC_TYPE_TISSUES = ("_AF",)  # disc_hexes() reads it at call time
    elif variant.startswith("np_lin:"):
        _, e_mpa, nu = variant.split(":")
        cards = export.material_cards

        def linear_nucleus(mats, template=None):
            out = cards(mats, template)
            return [LinearElastic("NP", float(e_mpa), float(nu)) if getattr(c, "name", "") == "NP" else c for c in out]

        submodel.material_cards = linear_nucleus
    elif variant != "base":
        raise SystemExit(f"unknown variant {variant!r}: base | np_c3d8 | np_lin:E:nu")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    patch(sys.argv[1])
    sys.exit(rom_explore.main(sys.argv[2:]))
