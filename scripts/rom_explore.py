"""Calibration explorer: the ROM of one model's functional units and/or lumbar model with config overrides,
the way docs/explanation/fe-model.md's calibration sweeps were measured (the same `solve_model` and `validate` as the rules).

    .venv/bin/python scripts/rom_explore.py OUT --units T2T3,T6T7,T10T11 [--lumbar] [--ribs]
        [--cases axial_left,axial_right] [--model model_08403] [--config config/config.yaml]
        [fe.annulus.fibres.angle_deg=43 fe.facets.clearance_mm=0.25 ...]

Overrides are dotted config paths with YAML values (``+a.b.c=value`` adds an optional key the config lacks,
e.g. ``+fe.annulus.fibres.k1_inner_mpa=1.17 +fe.annulus.fibres.k1_outer_mpa=1.8``); the deck is ``<results>/models/<model>.inp`` (make it
with ``snakemake -j2 results/models/<model>.inp``).  Prints the validation rows of the solved extractions
and the lumbar orderings; writes OUT/rom.csv (every ccx deck and log stays under OUT).  A unit case takes
~4 s on the default mean, a lumbar-model case 2-7 min on 2 cores.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import pandas as pd
import yaml


def override(cfg: dict, item: str) -> None:
    """Set ``a.b.c=value`` (value parsed as YAML) in the config dict; a clear error for an unknown key
    (``+a.b.c=value``: add the leaf c, which the config may lack, to the existing a.b)."""
    add = item.startswith("+")
    path, _, value = item.removeprefix("+").partition("=")
    if not value:
        raise SystemExit(f"override {item!r}: expected path=value")
    node, keys = cfg, path.split(".")
    for k in keys[:-1]:
        if not isinstance(node, dict) or k not in node:
            raise SystemExit(f"override {item!r}: config has no {path!r}")
        node = node[k]
    if not isinstance(node, dict) or (keys[-1] not in node and not add):
        raise SystemExit(f"override {item!r}: config has no {path!r}")
    node[keys[-1]] = yaml.safe_load(value)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("overrides", nargs="*", help="dotted.config.path=value")
    ap.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    ap.add_argument("--model", default=None, help="default: the config's rom.model")
    ap.add_argument("--units", default="", help="comma-separated units, e.g. T2T3,L3L4")
    ap.add_argument("--lumbar", action="store_true", help="also the lumbar model (rom.lumbar)")
    ap.add_argument("--ribs", action="store_true", help="also the rib-head variant of rib-bridged units")
    ap.add_argument("--cases", default="", help="comma-separated load cases (default: the config's)")
    args = ap.parse_intermixed_args(argv)

    from spinecohort.fe.export import read_deck_points
    from spinecohort.fe.materials import materials_from_config
    from spinecohort.layout import Layout
    from spinecohort.mesh.template import HexTemplate
    from spinecohort.rom.compare import orderings, validate_from_config
    from spinecohort.rom.run import solve_model

    cfg = yaml.safe_load(args.config.read_text())
    for item in args.overrides:
        override(cfg, item)
    rom = copy.deepcopy(cfg["rom"])
    rom["lumbar"]["enabled"] = args.lumbar
    rom["units"] = [u for u in args.units.split(",") if u]
    rom["all_effect"] = False
    rom["rib_heads"]["enabled"] = args.ribs
    if args.cases:
        rom["load_cases"] = args.cases.split(",")
    model = args.model or cfg["rom"]["model"]
    layout = Layout(cfg["results"])
    deck = Path(layout.model_file(model, "inp"))
    if not deck.exists():
        raise SystemExit(f"{deck} does not exist: make it with `snakemake -j2 {deck}`")
    template = HexTemplate.load(layout.template)
    table = solve_model(
        template, read_deck_points(deck, template), rom, args.out, model, materials_from_config(cfg["fe"])
    )
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "rom.csv", index=False)
    val = validate_from_config(table, rom)
    pd.set_option("display.width", 200)
    cols = ["segment", "motion", "side", "mode", "variant", "model_deg", "accept_low", "accept_high", "in_range"]
    print(" ".join(args.overrides) or "(config as is)")
    print(val[cols].to_string(index=False))
    print(
        f"in range: {int(val['in_range'].sum())} of {int(val['in_range'].notna().sum())} judged; "
        f"min load fraction {table['load_fraction'].min():.3f}"
    )
    for mode in ("lumbar", "unit"):
        o = orderings(table, mode=mode)
        if len(o):
            print(o.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
