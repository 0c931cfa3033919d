"""Where a ROM case stops converging: solve one load case of one extraction with every node's displacement
printed at every converged increment, then rank the hexes by their corner Jacobian (deformed / reference) and
the fibre and ligament springs by their strain at the last converged load fraction.

    .venv/bin/python scripts/rom_diagnose.py OUT --segment T10-S1 --case flexion [--cep-fraction 0.7]
        [--no-rim-fibres] [--rim-c3d8] [--rim-contact 0.3 --rim-stiffness 2000] [--drop-ligaments ITL]
        [--correction-tolerance 2] [--analyse-only] [fe.annulus.fibres.angle_deg=46 ...]
        [--guided] [--free-top-mm 4] [--fibre-toe 0.02] [--rim-d1 0.05]   (session 16-17 probes, docs/rom.md)

--cep-fraction relabels a whole-layer-CEP template's cartilage-endplate layers (no node moves, so the model
deck's coordinates stay valid): the hexes outside the cartilage join their disc's annulus set, fibre springs and
C3D8R included (session 13's representation); --rim-c3d8 puts them in the bone's C3D8 block (what
`template.cep_diameter_fraction` builds since session 15, the fibred D_<disc>_RIM sets); --no-rim-fibres leaves them
without fibre springs (session 14's rim, which cuts the fibres off the bone: docs/rom.md "Session 15").  Written for
sessions 14-15's question (docs/rom.md): why the T10-S1 model stalls with the annulus reaching the bony rim.  Prints
the status, the last converged load fraction, the fixed nodes' net reaction force (~0 under a pure moment), the
hexes with the smallest corner-Jacobian ratio (deformed / reference; < 0: inverted) per element block, the most stretched and shortened springs, every contact strut's state
(open, in its rounded corner, closed), each segment's rotation and the nodes of ccx's last largest residuals and
corrections (where Newton cycles).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import sys
from pathlib import Path

import numpy as np
import yaml


def relabel_cep(template, fraction: float):
    """The template with its CEP layers' hexes outside the ring nearest `fraction` of the diameter moved to the
    annulus set of their disc, and the set of the moved hexes (template hex ids)."""
    from spinecohort.mesh.template import ogrid

    grid = ogrid(dataclasses.replace(template.resolution, cep_diameter_fraction=fraction))
    ring = template.grid.quad_ring[np.arange(len(template.hexes)) % len(template.grid.quads)]
    elsets = dict(template.elsets)
    moved = []
    for name, idx in template.elsets.items():
        if not name.endswith("_CEP"):
            continue
        out = idx[ring[idx] > grid.cep_ring]
        elsets[name] = idx[ring[idx] <= grid.cep_ring]
        af = name[: -len("_CEP")] + "_AF"
        elsets[af] = np.sort(np.concatenate([template.elsets[af], out]))
        moved.append(out)
    g = dataclasses.replace(template.grid, cep_ring=grid.cep_ring)
    return dataclasses.replace(template, elsets=elsets, grid=g), np.concatenate(moved)


def add_rim_contact(model, template, share: float, stiffness_n_per_mm: float) -> None:
    """Compression-only struts across every disc of the submodel, between the two endplates' O-grid boundary nodes
    (16 per disc): no force until the disc has lost `share` of its local height there, then `stiffness_n_per_mm`
    (`spinecohort.fe.facets.strut_table`): the bony rims meeting through the compressed annulus (an experiment)."""
    from spinecohort.fe.abaqus import Section
    from spinecohort.fe.facets import strut_table

    sub_of = {int(t): i for i, t in enumerate(model.source_nodes) if t >= 0}
    n2 = len(template.grid.nodes)
    fe = model.fe
    first = sum(len(c) for _, c in fe.element_blocks.values())
    pairs = []
    for upper, lower in model.segments():
        up = template.nsets[f"EP_INF_{upper}"]
        lo = template.nsets[f"EP_SUP_{lower}"]
        up = {int(t) % n2: int(t) for t in up}
        lo = {int(t) % n2: int(t) for t in lo}
        pairs += [(sub_of[up[g]], sub_of[lo[g]]) for g in template.grid.outer if up[g] in sub_of and lo[g] in sub_of]
    conn = np.array(pairs, dtype=np.int64)
    fe.element_blocks["RIMS"] = ("SPRINGA", conn)
    length = np.linalg.norm(fe.nodes[conn[:, 0]] - fe.nodes[conn[:, 1]], axis=1)
    for k, h in enumerate(length):
        fe.element_sets[f"RIMC_{k + 1}"] = np.array([first + k])
        table = strut_table(share * h, stiffness_n_per_mm, h, blend_mm=0.05, reach_mm=0.4 * h * (1 - share))
        fe.sections.append(Section(elset=f"RIMC_{k + 1}", spring_force_elongation=table))
    print(f"rim contact: {len(conn)} struts, {length.min():.2f}-{length.max():.2f} mm, engaging at {share:.0%} lost")


def corner_jacobians(x: np.ndarray, hexes8: np.ndarray) -> np.ndarray:
    """(E, 8) det of the edge triad at each corner of C3D8-ordered hexes, x (N, 3) mm."""
    nb = np.array([[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]])
    c = x[hexes8]  # (E, 8, 3)
    e = c[:, nb] - c[:, :, None]  # (E, 8, 3, 3)
    return np.linalg.det(e)


def contact_states(fe, x0: np.ndarray, x1: np.ndarray, blocks=("FACETS", "RIMS")) -> list[str]:
    """One line per contact strut of `blocks`: its set, shortening (mm), the table's force (N) and slope (N/mm)
    there, and its state: open, in the rounded corner (stiffness rising, where Newton iterations can flip it)
    or closed."""
    table = {
        sec.elset: np.array(sec.spring_force_elongation)[:, ::-1] for sec in fe.sections if sec.spring_force_elongation
    }
    owner = {int(v[0]): k for k, v in fe.element_sets.items() if len(v) == 1 and k in table}
    lines, first = [], 0
    for name, (etype, conn) in fe.element_blocks.items():
        if name in blocks and etype == "SPRINGA":
            for i, (a, b) in enumerate(conn):
                t = table[owner[first + i]]  # (elongation mm, force N), ascending
                d = np.linalg.norm(x1[b] - x1[a]) - np.linalg.norm(x0[b] - x0[a])
                j = int(np.clip(np.searchsorted(t[:, 0], d), 1, len(t) - 1))
                slope = (t[j, 1] - t[j - 1, 1]) / (t[j, 0] - t[j - 1, 0])
                full = (t[1, 1] - t[0, 1]) / (t[1, 0] - t[0, 0])  # the closed strut's slope
                state = "open" if slope == 0 else ("closed" if np.isclose(slope, full) else "CORNER")
                f = np.interp(d, t[:, 0], t[:, 1])
                lines.append(
                    f"   {owner[first + i]:<24s} {state:<6s} shortened {-d:7.3f} mm  F {f:8.1f} N  k {slope:7.0f} N/mm"
                )
        first += len(conn)
    return lines


def cycling_nodes(log: Path, fe, last: int = 12) -> list[str]:
    """The nodes of ccx's last `last` 'largest correction' / 'largest residual' lines (where Newton cycles), with the
    element blocks that use them."""
    import re

    hits = re.findall(
        r"largest (residual force|correction to disp)= *(\S+) in node (\d+) and dof (\d)", log.read_text()
    )
    out = []
    for kind, val, node, dof in hits[-last:]:
        n = int(node) - 1
        used = [b for b, (_, c) in fe.element_blocks.items() if n < len(fe.nodes) and (c == n).any()]
        where = np.round(fe.nodes[n], 1) if n < len(fe.nodes) else "(rigid-body node)"
        out.append(f"   {kind:<18s} {float(val):10.3g} node {node} dof {dof} at {where} in {used}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("overrides", nargs="*")
    ap.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    ap.add_argument("--segment", default="T10-S1")
    ap.add_argument("--case", default="flexion")
    ap.add_argument("--cep-fraction", type=float, default=None)
    ap.add_argument("--no-rim-fibres", action="store_true")
    ap.add_argument("--rim-c3d8", action="store_true", help="the moved rim hexes as C3D8 (full integration)")
    ap.add_argument("--correction-tolerance", type=float, default=None, help="ccx C_n (run_case's attempt 2: 2.0)")
    ap.add_argument(
        "--rim-contact", type=float, default=None, help="rim contact struts engaging at this share of lost height"
    )
    ap.add_argument("--rim-stiffness", type=float, default=500.0, help="N/mm per rim strut once engaged")
    ap.add_argument("--drop-ligaments", default="", help="comma-separated ligament groups to leave out, e.g. ITL")
    ap.add_argument("--rim-d1", type=float, default=None, help="D1 (1/MPa) of the D_<disc>_RIM sets' ground substance only")
    ap.add_argument(
        "--free-top-mm", type=float, default=None, help="leave the loaded top's nodes this close (mm) above its inferior endplate out of its rigid body"
    )
    ap.add_argument("--guided", action="store_true", help="hold the top's rotation across the load's axis")
    ap.add_argument("--fibre-toe", type=float, default=None, help="fibre springs C1 at slack: a smoothstep toe to this strain")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--analyse-only", action="store_true", help="read OUT's .dat of an earlier (or running) solve")
    args = ap.parse_intermixed_args(argv)
    sys.path.insert(0, str(Path(__file__).parent))
    from rom_explore import override

    import spinecohort.rom.submodel as submodel
    from spinecohort.fe.calculix import CalculixError, parse_dat, run_ccx
    from spinecohort.fe.export import materials_from_config, read_deck_points
    from spinecohort.layout import Layout
    from spinecohort.mesh.template import RIM_TISSUE, HexTemplate
    from spinecohort.rom.deck import rom_deck_text
    from spinecohort.rom.kinematics import segment_rotations_deg
    from spinecohort.rom.run import Settings

    cfg = yaml.safe_load(args.config.read_text())
    for item in args.overrides:
        override(cfg, item)
    settings = Settings.from_config(copy.deepcopy(cfg["rom"]))
    layout = Layout(cfg["results"])
    template = HexTemplate.load(layout.template)
    points = read_deck_points(Path(layout.model_file(cfg["rom"]["model"], "inp")), template)
    moved = np.zeros(0, np.int64)
    if args.cep_fraction is not None:
        template, moved = relabel_cep(template, args.cep_fraction)
        print(f"CEP fraction {args.cep_fraction}: cep_ring {template.grid.cep_ring}, {len(moved)} hexes -> annulus")
    if args.no_rim_fibres and not len(moved):  # a template built with a partial CEP: its D_<disc>_RIM sets
        rims = [v for k, v in template.elsets.items() if k.endswith("_" + RIM_TISSUE)]
        moved = np.unique(np.concatenate(rims)) if rims else moved
    if args.no_rim_fibres and len(moved):
        real = submodel.annulus_fibres

        def fibres_off_rim(tpl, pts, mats, hex_ids=None):
            ids = np.flatnonzero(np.ones(len(tpl.hexes), bool)) if hex_ids is None else np.asarray(hex_ids)
            return real(tpl, pts, mats, np.setdiff1d(ids, moved))

        submodel.annulus_fibres = fibres_off_rim
    if args.rim_c3d8 and len(moved):
        import spinecohort.fe.export as export

        # the rim hexes in their own sets D_<disc>_RIM_AF (one element type per section), same material and axis
        for name in [k for k in template.elsets if k.endswith("_AF")]:
            rim = np.intersect1d(template.elsets[name], moved)
            template.elsets[name] = np.setdiff1d(template.elsets[name], moved)
            template.elsets[name[:-3] + "_RIM_AF"] = rim
            template.elset_kind[name[:-3] + "_RIM_AF"] = "hex"
        real_orient = export.disc_orientations

        def with_rim_axes(tpl, pts):
            o = real_orient(tpl, pts)
            return {**o, **{k + "_RIM": v for k, v in o.items()}}

        export.disc_orientations = with_rim_axes
        real_disc = export.disc_hexes

        def disc_but_rim(tpl, tissues=export.DISC_TYPE_TISSUES):
            mask = real_disc(tpl, tissues)
            mask[moved] = False  # -> the bone/CEP block, C3D8
            return mask

        export.disc_hexes = disc_but_rim
    if args.fibre_toe is not None:  # a probe: fibre springs whose slope rises from 0 over a toe (C1 at slack)
        import spinecohort.fe.fibres as fibres

        def toe_table(k1_mpa, k2, force_scale_mm2, length_mm, toe=args.fibre_toe):
            strains = np.unique(np.concatenate([np.linspace(0.0, toe, 9), fibres.TABLE_STRAINS]))
            x = np.clip(strains / toe, 0.0, 1.0)
            force = fibres.fibre_force_n(1.0 + strains, k1_mpa, k2, force_scale_mm2) * (3 * x**2 - 2 * x**3)
            return ((0.0, -float(length_mm)),) + tuple((float(f), float(e * length_mm)) for f, e in zip(force, strains))

        fibres.fibre_table = toe_table
    mats = materials_from_config(cfg["fe"])
    top, bottom = args.segment.split("-")
    model = submodel.extract_rom_model(
        template,
        points,
        top,
        bottom,
        materials=mats,
        hex_type=settings.hex_type,
        disc_hex_type=settings.disc_hex_type,
        nucleus_hex_type=settings.nucleus_hex_type,
        facets=mats.facets,
        ligament_groups=tuple(g for g in mats.ligaments if g not in args.drop_ligaments.split(",")),
    )
    if args.free_top_mm is not None:  # a probe: the loaded top potted only above its inferior endplate's bone
        hosts = model.fe.embedded_hosts()
        rb = model.rigid_nodes[top]
        axis = model.frames[top][:, 2]
        base = model.fe.nodes[np.intersect1d(model.endplate_nodes[top], hosts)] @ axis if len(hosts) else None
        if base is None or not len(base):
            raise SystemExit("--free-top-mm: the loaded top carries no fibre-tie hosts")
        in_hexes = np.isin(rb, model.fe.element_blocks["HEXES"][1])  # the arch's anchors stay rigid (no trusses)
        free = (model.fe.nodes[rb] @ axis < base.mean() + args.free_top_mm) & in_hexes
        model.rigid_nodes[top] = rb[~free]
        print(f"loaded top {top}: {free.sum()} nodes within {args.free_top_mm} mm of its inferior endplate left deformable")
    if args.rim_d1 is not None:  # a probe: the rim insertion's own volume response (docs/rom.md "Session 16")
        import dataclasses as dc

        from spinecohort.fe.abaqus import NeoHooke

        fe = model.fe
        fe.sections[:] = [
            dc.replace(sec, material="AF_RIM") if sec.elset.endswith("_" + RIM_TISSUE) else sec for sec in fe.sections
        ]
        fe.materials.append(NeoHooke("AF_RIM", mats.annulus_c10_mpa, args.rim_d1))
    if args.rim_contact is not None:
        add_rim_contact(model, template, args.rim_contact, args.rim_stiffness)
    args.out.mkdir(parents=True, exist_ok=True)
    kw = settings.deck_kw()
    if args.correction_tolerance is not None:
        kw["correction_tolerance"] = args.correction_tolerance
    if args.guided:  # run_case's fifth attempt: the top turns about the load's axis only
        kw["guided"] = True
    text = rom_deck_text(model, args.case, settings.moment_nmm, **kw)
    text = text.replace("*END STEP", "*NODE PRINT, NSET=NALL\nU\n*END STEP")
    deck = args.out / f"diag_{args.case}.inp"
    dat = args.out / f"diag_{args.case}.dat"
    if args.analyse_only:
        blocks, status = parse_dat(dat.read_text()), "analysed as found"
    else:
        deck.write_text(text)
        try:
            res = run_ccx(deck, args.out, threads=args.threads, timeout_s=7200)
            blocks, status = res.node_prints, "converged"
        except CalculixError as exc:
            blocks, status = parse_dat(dat.read_text()), str(exc).splitlines()[-1]
    alln = [b for b in blocks if b.node_set.upper() == "NALL"]
    last = alln[-1]
    print(f"{status}; last converged load fraction {last.time:.4f}")
    rf = [b for b in blocks if b.node_set.upper() == "FIXED" and b.time == last.time]
    if rf:  # a pure moment: ~0 (session 16: fibre ties on fixed nodes hid their share, `FEModel.embedded_hosts`)
        print(f"net reaction force of the fixed nodes: {np.round(np.asarray(rf[-1].values).sum(0), 2)} N")
    u = np.zeros_like(model.fe.nodes)
    u[np.asarray(last.node_ids, int) - 1] = last.values
    x0, x1 = model.fe.nodes, model.fe.nodes + u
    # where the motion goes: each segment's rotation (lateral, anterior, cranial deg) at the last converged load
    for (up, lo), r in segment_rotations_deg(model, dict(enumerate(u))).items():
        print(f"segment {up}-{lo}: rotation {np.round(r, 2)} deg")
    first = 0
    for name, (etype, conn) in model.fe.element_blocks.items():
        if etype.startswith("C3D"):
            h = conn[:, :8]
            ratio = corner_jacobians(x1, h) / corner_jacobians(x0, h)
            worst = np.argsort(ratio.min(1))[:12]
            print(f"block {name} ({etype}, {len(h)}): corner J ratio min {ratio.min():.3f} max {ratio.max():.3f}")
            for e in worst:
                z = x0[h[e]].mean(0)
                sets = [k for k, v in model.fe.element_sets.items() if (first + e) in set(v.tolist())][:3]
                print(f"   el {first + e + 1}: J ratio {ratio[e].min():.3f} at {np.round(z, 1)} sets {sets}")
        elif etype.startswith("SPRING"):
            lo = np.linalg.norm(x0[conn[:, 1]] - x0[conn[:, 0]], axis=1)
            ln = np.linalg.norm(x1[conn[:, 1]] - x1[conn[:, 0]], axis=1)
            strain = ln / lo - 1
            worst = np.concatenate([np.argsort(-strain)[:8], np.argsort(strain)[:4]])  # most stretched, shortened
            print(
                f"block {name} ({etype}, {len(conn)}): strain max {strain.max():.3f}, >0.3: {(strain > 0.3).sum()}, "
                f"min {strain.min():.4f} (el {first + int(np.argmin(strain)) + 1}, shortened "
                f"{-(ln - lo).min():.3f} mm)"
            )
            for e in worst:
                print(
                    f"   el {first + e + 1}: strain {strain[e]:.3f}, L0 {lo[e]:.3f} mm at {np.round(x0[conn[e]].mean(0), 1)}"
                )
        first += len(conn)
    print("contact struts at the last converged load (CORNER: stiffness rising over fe.facets.blend_mm):")
    print("\n".join(contact_states(model.fe, x0, x1)))
    log = args.out / f"diag_{args.case}.log"
    if log.exists():  # run_ccx's stdout; absent for --analyse-only of a foreign run
        print("where the last Newton iterations cycle (ccx's largest residual / correction):")
        print("\n".join(cycling_nodes(log, model.fe)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
