"""Running the ROM analyses: one ccx process per load case (strict log check, one retry with smaller
increments, the ROM at the last converged load fraction otherwise), the per-segment ROM table, and every
configured extraction of one model (`solve_model`), configured by `Settings` (the ``rom:`` config block).
Units: mm, N, N.mm, degrees."""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.fe.materials import DEFAULT_MATERIALS, FEMaterials
from spinecohort.fe.pure_moment import LOAD_CASES
from spinecohort.mesh.template import HexTemplate
from spinecohort.rom.deck import load_vector_nmm, rom_deck_text
from spinecohort.rom.kinematics import segment_rotations_deg
from spinecohort.rom.loads import facet_forces, nucleus_pressure
from spinecohort.rom.reaction import generalised_load, reactions
from spinecohort.rom.ribs import RIB_SEGMENTS, RibHeads
from spinecohort.rom.submodel import (
    RomError,
    RomModel,
    check_elements,
    extract_rom_model,
    parse_unit,
)

log = logging.getLogger(__name__)

#: ccx's words for a load step it could not finish (the increment cut below its minimum, too many cutbacks),
#: and the solver wrapper's for a run stopped at rom.timeout_s (a step crawling in 1e-5 increments near a
#: limit load): both keep the ROM at the last converged load fraction, flagged, rather than losing the model.
#: ccx 2.20's fibre law aborting ("*ERROR in umat_elastic_fiber": it reads k2 before assigning it;
#: docs/explanation/fe-model.md) depends on the iterates, so it is retried with the other attempts' settings like a non-convergence
NONCONVERGENCE = re.compile(
    r"increment size smaller than minimum|too many cutbacks|divergence|timed out after|umat_elastic_fiber",
    re.IGNORECASE,
)

# ccx warnings that are harmless in these analyses (anything else fails the run): none so far
ALLOWED_WARNINGS: tuple[str, ...] = ()


@dataclass
class CaseResult:
    case: str
    rotations_deg: dict[tuple[str, str], np.ndarray]  # segment -> (lateral, anterior, cranial) components
    top_rotation_deg: np.ndarray  # ROT NODE rotation of the top vertebra (global x, y, z)
    curve: np.ndarray  # (T, 2): load fraction, top rotation about the load axis in degrees
    seconds: float
    peak_rss_mb: float
    load_fraction: float = 1.0  # of the moment reached (< 1: ccx did not converge; ROM at that load)
    attempts: int = 1
    #: the moment (N.mm, global) the fixation carries at the last printed load: minus the fixed nodes' reaction
    #: moment (`spinecohort.rom.reaction`); the physical moment on the top for a load without net force
    carried_nmm: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    reaction_force_n: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))  # net, ~0
    cload_nmm: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))  # on the ROT NODE
    target_nmm: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))  # the load case's
    moment_iterations: int = 0  # solves after the first with the *CLOAD corrected (`run_case`)
    #: the moment (N.mm, global) that held a guided top's rotation on the load's axis: what the base carried
    #: beyond the load, across the axis (`guide_moment`); zero for a free top
    guide_nmm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    #: per disc: nucleus pressure (MPa), volume, elements at the last printed load (`spinecohort.rom.loads`)
    idp: pd.DataFrame | None = None
    #: per facet joint side and kind: contact force (N, compression positive) at the last printed load
    facets: pd.DataFrame | None = None


def run_case(
    model: RomModel,
    case: str,
    workdir: str | Path,
    moment_nmm: float = 7500.0,
    threads: int = 1,
    timeout_s: float = 3600.0,
    job: str | None = None,
    moment_iterations: int = 0,
    **deck_kw,
) -> CaseResult:
    """Write the deck of one load case into workdir, run ccx on it (strict log check), read the ROM.

    moment_iterations: 0 = the load case's moment vector on the ROT NODE (ccx's generalised force: the
    physical moment differs from it once the top has turned about an axis other than the moment's,
    `spinecohort.rom.reaction.physical_moment`); n > 0 = n more solves, each with the *CLOAD that exerts the
    load case's moment at the previous solve's rotation (decks ``<job>_m<i>.inp``; the ROM is the last's)."""
    from spinecohort.fe.calculix import CalculixError, CcxResult, parse_dat, run_ccx

    check_elements(model)  # an inverted hex never reaches the solver
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    job = job or f"rom_{case}"
    deck = workdir / f"{job}.inp"
    # Non-convergence (tension-only springs, facet gaps and fibres switching, a soft unit at large rotation)
    # is a property of the load case, not a broken run.  Second attempt, measured on the T6-T7 unit's right
    # lateral bending (stuck at 99.3 % of the load with the strict criterion and with smaller increments: the
    # Newton iterations cycled between three states, residual 5e-4 N but a 100 % displacement correction):
    # keep the residual criterion (0.5 % of the reference force) and relax only the displacement-correction
    # one (C_n 0.01 -> 2); it reached the full load and agreed with the strict run to 0.001 deg at the load
    # both reached (docs/explanation/fe-model.md).  Third: smaller increments with the relaxed C_n (with the
    # C3D20R nucleus the lumbar extension's first 5 % increment aborts in ccx's fibre law, so the relaxed attempt
    # never gets past it, and smaller strict increments cycle at 98.5 %).  Fourth: strict with smaller increments.
    # Fifth, guided: the third's settings with the top turning about the load's axis only (`guide_equations`).
    # With the annulus at the bony rim the T10-S1 flexion reaches an out-of-plane bifurcation at 92 % of the
    # load (the free top's lateral and axial rotations go singular; moment-rotation curve still stiffening);
    # held, the path is the free one to 0.01 % before it and reaches the load (docs/explanation/fe-model.md); the
    # moment that held it is reported (`CaseResult.guide_nmm`, the ROM table's guide_moment_nmm).
    # Then keep the ROM at the last converged load fraction, flagged, instead of losing the other load cases.
    relaxed_kw = {**deck_kw, "correction_tolerance": 2.0}
    retry_kw = {
        **deck_kw,
        "initial_increment": min(0.02, deck_kw.get("initial_increment", 0.1)),
        "max_increment": min(0.05, deck_kw.get("max_increment", 0.25)),
        "min_increment": min(1e-6, deck_kw.get("min_increment", 1e-4)),
        "max_increments": max(400, deck_kw.get("max_increments", 100)),
    }
    seconds = peak = 0.0
    target = load_vector_nmm(model, case, moment_nmm)
    load = None  # the first solve: the load case's moment vector as the ROT NODE's *CLOAD
    coords = {i + 1: x for i, x in enumerate(model.fe.nodes)}  # deck node id -> mm, for the reactions
    for iteration in range(int(moment_iterations) + 1):
        name = job if iteration == 0 else f"{job}_m{iteration}"
        deck = workdir / f"{name}.inp"
        guided_kw = {**retry_kw, "correction_tolerance": 2.0, "guided": True}
        attempts = [deck_kw, relaxed_kw, {**retry_kw, "correction_tolerance": 2.0}, retry_kw, guided_kw]
        for attempt, kw in enumerate(attempts, start=1):
            deck.write_text(rom_deck_text(model, case, moment_nmm, load_nmm=load, **kw))
            t0 = time.perf_counter()
            try:
                res = run_ccx(deck, workdir, threads=threads, timeout_s=timeout_s, allowed_warnings=ALLOWED_WARNINGS)
            except CalculixError as exc:
                if not NONCONVERGENCE.search(str(exc)):
                    raise
                log.warning("%s: ccx did not converge (attempt %d): %s", deck, attempt, str(exc).splitlines()[-1])
                dat = workdir / f"{name}.dat"
                res = CcxResult(
                    1,
                    "",
                    parse_dat(dat.read_text()) if dat.exists() else [],
                    workdir,
                    name,
                    time.perf_counter() - t0,
                    float("nan"),
                )
                converged = False
            else:
                converged = True
            seconds += res.seconds
            peak = np.nanmax([peak, res.peak_rss_mb])
            if converged:
                break
        rot_prints = [b for b in res.node_prints if b.node_set.upper() == "ROTTOP" and b.quantity.startswith("displ")]
        if moment_iterations:
            _log_iteration(model, case, deck, res.node_prints, coords, iteration, load, target)
        # a guided top turns about a fixed axis, to which the moment about it is conjugate: nothing to correct
        if not converged or not rot_prints or iteration == moment_iterations or kw.get("guided"):
            break
        # the *CLOAD is the generalised force conjugate to the ROT NODE's rotation vector: the load that
        # exerts the moment `target` at the rotation reached (a fixed point: the next solve turns a little
        # differently; `moment_iterations` solves refine it)
        load = generalised_load(target, rot_prints[-1].values[0])
        log.info("%s: moment iteration %d, *CLOAD %s N.mm", deck, iteration + 1, np.round(load, 1))
    ep_prints = [b for b in res.node_prints if b.node_set.upper() == "EPNODES"]
    if not rot_prints or not ep_prints:
        raise RomError(f"ccx run {deck} printed no displacements (log {workdir / (job + '.log')})")
    last = ep_prints[-1]
    if converged and abs(last.time - 1.0) > 1e-6:
        raise RomError(f"ccx run {deck} stopped at load fraction {last.time:g}, not 1 (no convergence?)")
    disp = {int(i) - 1: v for i, v in zip(last.node_ids, last.values)}
    axis, sign = LOAD_CASES[case]
    load_axis = model.frames[model.top][:, axis]
    curve = np.array([[b.time, sign * np.degrees(b.values[0] @ load_axis)] for b in rot_prints])
    rf = _reaction_at(coords, res.node_prints, last.time)
    return CaseResult(
        case,
        segment_rotations_deg(model, disp),
        np.degrees(rot_prints[-1].values[0]),
        curve,
        seconds,
        peak,
        float(last.time),
        attempt,
        rf.carried_nmm() if rf else np.full(3, np.nan),
        rf.force_n if rf else np.full(3, np.nan),
        np.asarray(load if load is not None else target, dtype=np.float64),
        np.asarray(target, dtype=np.float64),
        iteration,
        guide_moment(rf.carried_nmm(), target) if rf and kw.get("guided") else np.zeros(3),
        nucleus_pressure(model.fe, res.node_prints, last.time),
        facet_forces(model.fe, res.node_prints, last.time),
    )


def guide_moment(carried_nmm: np.ndarray, load_nmm: np.ndarray) -> np.ndarray:
    """The moment that guides a guided top (N.mm, global): what the fixed base carries beyond the load, across
    the load's axis.  Pure moments: base + load + guide = 0, so guide = carried - load; its part along the
    axis is the elements' own moment leak (docs/explanation/fe-model.md), not guidance, and is left out."""
    m = np.asarray(load_nmm, dtype=np.float64)
    axis = m / np.linalg.norm(m)
    extra = np.asarray(carried_nmm, dtype=np.float64) - m
    return extra - (extra @ axis) * axis


def _reaction_at(coords: dict, prints, time: float):
    """The fixed nodes' `Reaction` printed at step time ``time`` (None if there is none)."""
    rf = [r for r in reactions(coords, prints) if abs(r.time - time) < 1e-9]
    return rf[-1] if rf else None


def _log_iteration(model: RomModel, case: str, deck: Path, prints, coords, iteration: int, load, target) -> None:
    """One moment iteration's *CLOAD, carried moment, top rotation and segment ROMs (the log)."""
    ep = [b for b in prints if b.node_set.upper() == "EPNODES"]
    rot = [b for b in prints if b.node_set.upper() == "ROTTOP"]
    if not ep or not rot:
        return
    rf = _reaction_at(coords, prints, ep[-1].time)
    axis, sign = LOAD_CASES[case]
    rows = segment_rotations_deg(model, {int(i) - 1: v for i, v in zip(ep[-1].node_ids, ep[-1].values)})
    log.info(
        "%s: moment iteration %d at load %.4f: *CLOAD %s, carried %s (target %s) N.mm, top rotation %s deg, ROM %s deg",
        deck,
        iteration,
        ep[-1].time,
        np.round(target if load is None else load, 1),
        np.round(rf.carried_nmm(), 1) if rf else "?",
        np.round(target, 1),
        np.round(np.degrees(rot[-1].values[0]), 3),
        {f"{u}-{lo}": round(float(sign * c[axis]), 3) for (u, lo), c in rows.items()},
    )


def carried_fraction(r: CaseResult) -> float:
    """Share of the load case's moment that the fixation carries at the last printed load, along the load's
    direction: carried . target / (load_fraction |target|^2).  1 for a model in equilibrium; C3D8R discs
    leak some (docs/explanation/fe-model.md).  NaN without reaction prints."""
    t = np.asarray(r.target_nmm, dtype=np.float64)
    den = float(r.load_fraction) * float(t @ t)
    return float(np.asarray(r.carried_nmm) @ t / den) if den > 0 and np.all(np.isfinite(r.carried_nmm)) else np.nan


def rom_table(model: RomModel, results: list[CaseResult], model_id: str, mode: str) -> pd.DataFrame:
    """One row per segment and load case: primary ROM (deg, positive in the load direction), the
    coupled rotations about the other two axes, and the share of the moment the fixation carries."""

    rows = []
    for r in results:
        axis, sign = LOAD_CASES[r.case]
        carried = carried_fraction(r)
        for (up, lo), comp in r.rotations_deg.items():
            rows.append(
                {
                    "model": model_id,
                    "mode": mode,
                    "segment": f"{up}-{lo}",
                    "load_case": r.case,
                    "rom_deg": sign * comp[axis],
                    "lateral_deg": comp[0],
                    "anterior_deg": comp[1],
                    "cranial_deg": comp[2],
                    "load_fraction": r.load_fraction,
                    "moment_carried_fraction": round(carried, 4),
                    "attempts": r.attempts,
                    "guide_moment_nmm": round(float(np.linalg.norm(r.guide_nmm)), 1),
                    "solve_s": round(r.seconds, 2),
                    "peak_rss_mb": round(r.peak_rss_mb, 1),
                }
            )
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------------------------------
# one model: every extraction mode and load case


#: keys of the ``rom:`` block that only the comparison and the study rules read (not the solver)
REPORT_KEYS = (
    "model",
    "acceptance_sd",
    "seed_acceptance_sd",
    "rib_correction",
    "references",
    "sensitivity",
    "mode_levels",
    "mode_units",
    "convergence",
)


def solver_config(rom: dict) -> dict:
    """The part of a ``rom:`` block the solver reads: what a cached or Snakemake-tracked solution depends on
    (editing references, criteria or the study lists re-solves nothing)."""
    return {k: v for k, v in rom.items() if k not in REPORT_KEYS}


@dataclass(frozen=True)
class Settings:
    """The solver part of the ``rom:`` config block (docs/reference/config.md); the comparison keys (``model``,
    ``references``, ``acceptance_sd``) are read by the comparison code, not here."""

    moment_nmm: float = 7500.0
    load_cases: tuple[str, ...] = tuple(LOAD_CASES)
    hex_type: str = "C3D8"
    disc_hex_type: str = "C3D8R"  # annulus (docs/explanation/fe-model.md "Elements")
    nucleus_hex_type: str = "C3D20R"  # nucleus: C3D8R leaks moment, C3D8 locks (docs/explanation/fe-model.md)
    reference_force_n: float | None = 500.0
    nlgeom: bool = True
    initial_increment: float = 0.05
    min_increment: float = 1e-4
    max_increment: float = 0.1
    max_increments: int = 200
    lumbar: tuple[str, str] | None = ("T10", "S1")  # (top, bottom), None = no lumbar model
    #: the lumbar model's top turns about the load's axis only in every attempt (`rom_deck_text(guided=True)`):
    #: free, the T10-S1 model with the annulus at the bony rim bifurcates out of plane short of the load
    #: (flexion 92 %, lateral bending 85.6 %) after 20+ min of Newton cycling per case (docs/explanation/fe-model.md)
    lumbar_guided: bool = False
    units: tuple[tuple[str, str], ...] = ()  # functional units (upper, lower vertebra)
    threads: int = 2
    timeout_s: float = 7200.0
    #: solves after the first with the ROT NODE's *CLOAD corrected to exert the physical moment (`run_case`)
    moment_iterations: int = 0
    #: the specimens' rib heads (`spinecohort.rom.ribs`): units they bridge are also solved with them
    rib_heads: RibHeads | None = None

    @classmethod
    def from_config(cls, block: dict) -> Settings:
        """From the ``rom:`` block (keys not named here are ignored: they belong to the comparison)."""
        names = {f.name for f in dataclasses.fields(cls)}
        p = {k: v for k, v in block.items() if k in names}
        lumbar = p.pop("lumbar")
        ribs = RibHeads.from_config(p.pop("rib_heads", None))
        return cls(
            **{k: v for k, v in p.items() if k not in ("units", "load_cases")},
            rib_heads=ribs,
            load_cases=tuple(p["load_cases"]),
            lumbar=(lumbar["top"], lumbar["bottom"]) if lumbar["enabled"] else None,
            lumbar_guided=bool(lumbar.get("guided", False)),
            units=tuple(parse_unit(u) for u in p["units"]),
        )

    def deck_kw(self) -> dict:
        """The step controls `rom_deck_text` takes."""
        return dict(
            nlgeom=self.nlgeom,
            initial_increment=self.initial_increment,
            min_increment=self.min_increment,
            max_increment=self.max_increment,
            max_increments=self.max_increments,
            average_force_n=self.reference_force_n,
        )


def units_only(rom: dict, units) -> dict:
    """The ``rom`` block solving the functional units `units` alone: no lumbar model, no rib heads (the rib-free
    model the exported decks are); the solver settings unchanged."""
    return {
        **rom,
        "lumbar": {**rom["lumbar"], "enabled": False},
        "rib_heads": {**rom.get("rib_heads", {}), "enabled": False},
        "units": list(units),
    }


def analyses(settings: Settings) -> list[tuple[str, str, str]]:
    """(mode, top, bottom) of every ROM model the settings ask for: 'lumbar' and one 'unit' per FU."""
    out = []
    if settings.lumbar is not None:
        out.append(("lumbar", *settings.lumbar))
    for unit in settings.units:
        out.append(("unit", *unit))
    if not out:
        raise ValueError("rom: neither the lumbar model nor any functional unit is enabled")
    return out


#: the ROM models' variants: (heading suffix, ccx job suffix) of each
VARIANTS = {"intact": ("", ""), "no_ALL": (" no ALL", "_noALL"), "rib_heads": (" with rib heads", "_ribs")}


def variant_plan(
    settings: Settings, variants: Collection[str], include_all: bool = True
) -> list[tuple[str, str, str, str, dict]]:
    """(mode, top, bottom, variant, what differs from the intact model) of every ROM model `solve_model_loads`
    builds: per analysis (`analyses`) the asked `variants` that apply to it ('no_ALL' needs an ALL and an
    extension case, 'rib_heads' the settings' rib heads and a rib-bridged unit)."""
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        raise ValueError(f"unknown ROM variant(s) {sorted(unknown)} ({', '.join(VARIANTS)})")
    plan = []
    for mode, top, bottom in analyses(settings):
        if "intact" in variants:
            plan.append((mode, top, bottom, "intact", {}))
        if "no_ALL" in variants and "extension" in settings.load_cases and include_all:
            plan.append((mode, top, bottom, "no_ALL", {"include_all": False}))
        ribbed = mode == "unit" and (top, bottom) in RIB_SEGMENTS
        if "rib_heads" in variants and settings.rib_heads is not None and ribbed:
            plan.append((mode, top, bottom, "rib_heads", {"ribs": settings.rib_heads}))
    return plan


def solve_model_loads(
    template: HexTemplate,
    points: np.ndarray,
    settings: Settings | dict,
    workdir: str | Path,
    model_id: str,
    materials: FEMaterials | None = None,
    load_prints: bool = True,
    variants: Collection[str] = ("intact", "rib_heads"),
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """ROM table of one model for every configured extraction and load case of its `variants` ('intact'; 'rib_heads':
    the rib-bridged units with their rib heads, if the settings enable them; 'no_ALL': extension without the ALL),
    and the nucleus pressure of every disc and the facet force of every joint side per
    case (`spinecohort.rom.loads`; columns model, mode, variant, unit, then `CaseResult.idp` / `.facets`'s,
    load_case, load_fraction).  settings: `Settings` or the config's ``rom:`` block.  Decks, ccx logs and .dat
    files stay in ``workdir/<mode>_<top><bottom>/``.  Load cases run in parallel, ``settings.threads``
    single-threaded ccx processes at a time.  load_prints False: the decks print no nucleus stresses (a lumbar
    case's .dat is ~10x larger with them: 11-16 MB against 1-1.6 MB) and the pressures and forces are NaN."""
    from concurrent.futures import ThreadPoolExecutor

    cfg = settings if isinstance(settings, Settings) else Settings.from_config(settings)
    mats = DEFAULT_MATERIALS if materials is None else materials
    deck_kw = cfg.deck_kw()
    kw = dict(
        materials=mats,
        hex_type=cfg.hex_type,
        disc_hex_type=cfg.disc_hex_type,
        nucleus_hex_type=cfg.nucleus_hex_type,
        facets=mats.facets,
    )
    jobs = []
    for mode, top, bottom, variant, extra in variant_plan(cfg, variants, mats.include_all):
        sub = Path(workdir) / f"{mode}_{top}{bottom}"
        label, suffix = VARIANTS[variant]
        heading = f"{model_id} ROM {mode} {top}-{bottom}{label}"
        model = extract_rom_model(template, points, top, bottom, heading=heading, **kw, **extra)
        msj = check_elements(model)
        log.info(
            "%s %s %s-%s (%s): %d nodes, %d elements, ligaments %s, min scaled Jacobian %.3f",
            model_id,
            mode,
            top,
            bottom,
            variant,
            len(model.fe.nodes),
            model.fe.n_elements,
            model.ligament_groups,
            msj,
        )
        cases = ["extension"] if variant == "no_ALL" else cfg.load_cases
        for case in cases:
            jobs.append((mode, variant, model, case, sub, f"rom_{case}{suffix}"))

    def run(job):
        mode, variant, model, case, sub, name = job
        r = run_case(
            model,
            case,
            sub,
            moment_nmm=cfg.moment_nmm,
            threads=1,
            timeout_s=cfg.timeout_s,
            job=name,
            moment_iterations=cfg.moment_iterations,
            **{**deck_kw, "guided": cfg.lumbar_guided and mode == "lumbar", "load_prints": load_prints},
        )
        log.info(
            "%s %s %s-%s %s (%s): %.1f s, %.0f MB, top rotation %.2f deg, %d increments; moment carried %s N.mm "
            "(load case %s), net reaction force %s N",
            model_id,
            mode,
            model.top,
            model.vertebrae[-1],
            case,
            variant,
            r.seconds,
            r.peak_rss_mb,
            r.curve[-1, 1],
            len(r.curve),
            np.round(r.carried_nmm, 1),
            np.round(r.target_nmm, 1),
            np.round(r.reaction_force_n, 4),
        )
        head = {"model": model_id, "mode": mode, "variant": variant, "unit": f"{model.top}-{model.vertebrae[-1]}"}
        table = rom_table(model, [r], model_id, mode)
        table.insert(2, "variant", variant)
        table.insert(3, "unit", head["unit"])
        case = {"load_case": r.case, "load_fraction": r.load_fraction}
        return table, *(t.assign(**case).pipe(_lead, head) for t in (r.idp, r.facets))

    with ThreadPoolExecutor(max_workers=max(1, int(cfg.threads))) as pool:
        out = list(pool.map(run, jobs))
    return tuple(pd.concat([o[k] for o in out], ignore_index=True) for k in range(3))


def _lead(table: pd.DataFrame, columns: dict) -> pd.DataFrame:
    """`table` with the constant `columns` first."""
    return pd.concat([pd.DataFrame(columns, index=table.index), table], axis=1)


def solve_model(*args, **kwargs) -> pd.DataFrame:
    """The ROM table of `solve_model_loads` (same arguments), solved without the load prints."""
    return solve_model_loads(*args, **{"load_prints": False, **kwargs})[0]
