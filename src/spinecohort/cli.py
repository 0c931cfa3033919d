"""Command-line entry point ``spinecohort``: the package's functions without Snakemake."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from spinecohort.layout import Layout

DEFAULT_CONFIG = Path("config/config.yaml")


def _scalars(report: dict) -> dict:
    """The scalar entries of a repair report, for one line of output (its per-node arrays stay out)."""
    return {k: v for k, v in report.items() if isinstance(v, (bool, int, float, str))}


def _add_config_args(parser: argparse.ArgumentParser) -> None:
    """--config and --results, shared by every command that reads a pipeline's results."""
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="pipeline config (default: %(default)s)")
    parser.add_argument("--results", type=Path, help="results folder (default: the config's)")


def _config_and_layout(args: argparse.Namespace) -> tuple[dict, Layout]:
    """The config (validated keys are the pipeline's business; the CLI reads what it needs) and the results tree."""
    import yaml

    if not Path(args.config).is_file():
        raise ValueError(f"{args.config} does not exist; pass --config (the pipeline's config.yaml)")
    cfg = yaml.safe_load(Path(args.config).read_text())
    return cfg, Layout(args.results or cfg["results"])


def _generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from spinecohort.cohort.loading import write_cohort_folder
    from spinecohort.cohort.synthetic import generate_cohort

    bar = tqdm(total=args.n, desc="patients", unit="patient", disable=args.quiet)

    def progress(done, total):
        bar.update(done - bar.n)

    c = generate_cohort(args.n, seed=args.seed, resolution=args.resolution, noise_mm=args.noise_mm, progress=progress)
    bar.close()
    write_cohort_folder(args.out, c.ids, c.vertices, c.faces, c.landmarks, c.table)
    print(
        f"{len(c.ids)} patients ({c.n_candidates} candidates drawn), {c.vertices.shape[1]} vertices each -> {args.out}"
    )
    return 0


def _write_folder(args: argparse.Namespace) -> int:
    from spinecohort.cohort.user_folder import write_user_folder

    if args.generator == "real":  # the bones of `register.reference: real`
        from spinecohort.cohort.real import generate_real_cohort
        from spinecohort.cohort.register import real_reference

        c, bone = generate_real_cohort(args.n, seed=args.seed), real_reference().bone
    else:  # the bones of `register.reference: synthetic`
        from spinecohort.cohort.register import bone_labels
        from spinecohort.cohort.synthetic import generate_cohort

        c = generate_cohort(args.n, seed=args.seed, resolution=args.resolution, noise_mm=args.noise_mm)
        bone = bone_labels(c.vertices[0], c.faces, c.landmarks)
    written = write_user_folder(args.out, c.ids, c.vertices, c.faces, bone, c.table, args.per_bone, args.remesh_seed)
    kind = "one folder per patient, one file per bone" if args.per_bone else "one mesh per patient"
    print(f"{len(c.ids)} patients re-triangulated ({kind}), {len(written)} files -> {args.out}")
    return 0


def _check(args: argparse.Namespace) -> int:
    from spinecohort.cohort.loading import load_cohort

    folder = Path(args.folder)
    stls = sorted(folder.glob("*.stl"))
    c = load_cohort(
        stls, args.sheet or folder / "patients.csv", args.landmarks or folder / "landmarks.json", units=args.units
    )
    ext = c.points.max(1) - c.points.min(1)
    print(f"{len(c.ids)} patients, {c.points.shape[1]} vertices, {len(c.faces)} triangles, in correspondence")
    print(f"extent (mm): {np.round(ext.mean(0), 1)} on average; sheet columns: {', '.join(c.table.columns)}")
    return 0


def _ssm_info(args: argparse.Namespace) -> int:
    from spinecohort.ssm.model import SSM

    ssm = SSM.load(args.ssm)
    print(f"{ssm.n_train} training shapes, {ssm.mean.shape[0]} vertices, {ssm.n_modes} modes")
    for t in (0.8, 0.9, 0.95, 0.99):
        print(f"  {100 * t:.0f} % of the variance: {ssm.modes_for_variance(t)} modes")
    sd = np.sqrt(ssm.eigenvalues[:10])
    print(
        "  SD of the first modes (mm, RMS per vertex): "
        + ", ".join(f"{s / np.sqrt(ssm.mean.shape[0]):.2f}" for s in sd)
    )
    return 0


def _export(args: argparse.Namespace) -> int:
    from spinecohort.cohort.loading import load_cohort_npz
    from spinecohort.fe.models import check_load_options, virtual_model, write_model
    from spinecohort.mesh.hex_ssm import HexSSM
    from spinecohort.mesh.template import HexTemplate
    from spinecohort.ssm.model import SSM

    check_load_options(args.format, args.load, args.guided)  # before any file is read
    if args.release and _is_url(args.release):  # the stored coordinates, read over HTTP; nothing downloaded
        from spinecohort.release.remote import RemoteRelease

        remote = RemoteRelease(args.release, cache_dir=args.cache_dir)
        vm, template, src = remote.virtual_model(args.model_id)
        hex_type = src["hex_type"]
        faces = lambda: np.load(remote.file("model_inputs/faces.npy"), allow_pickle=False)  # noqa: E731
    else:
        if args.release:  # a release bag: its model_inputs/ hold everything (no config, no Snakemake)
            from spinecohort.release import release_model_inputs

            src = release_model_inputs(args.release)
            grid, hex_type = src["grid"], src["hex_type"]
            faces = lambda: np.load(src["faces"], allow_pickle=False)  # noqa: E731
        else:
            cfg, layout = _config_and_layout(args)
            grid, hex_type = cfg["grid"], cfg["template"]["hex_type"]
            src = {"ssm": layout.ssm, "hex_ssm": layout.hex_ssm, "template": layout.template, "fe": cfg.get("fe")}
            faces = lambda: load_cohort_npz(layout.cohort).faces  # noqa: E731
        template = HexTemplate.load(src["template"])
        vm = virtual_model(
            args.model_id, SSM.load(src["ssm"]), HexSSM.load(src["hex_ssm"]), template, grid["n_modes"], grid["levels"]
        )
    out = args.out or Path(f"model_{vm.model_id:05d}.{args.format}")
    from spinecohort.fe.materials import materials_from_config

    write_model(
        vm,
        args.format,
        out,
        template,
        faces(),
        hex_type,
        materials=materials_from_config(src["fe"]),
        load=args.load,
        moment_nmm=1000.0 * args.moment_nm,
        top=args.top,
        guided=args.guided,
    )
    print(f"model_{vm.model_id:05d} (weights {vm.weights.tolist()} SD) -> {out}; Jacobian check: {_scalars(vm.repair)}")
    return 0


def _is_url(source) -> bool:
    return str(source).lower().startswith(("http://", "https://"))


def _verify(args: argparse.Namespace) -> int:
    from spinecohort.release import BAG_ZIP, verify_deposit, verify_release

    if (args.release / BAG_ZIP).is_file():  # a downloaded deposit: the bag put back together, then checked
        rep = verify_deposit(args.release, processes=args.processes, workdir=args.tmpdir)
    else:
        rep = verify_release(args.release, processes=args.processes, store=not args.no_store)
    store = f"; the store zip holds {rep['shards']} intact shards of {rep['models']} models" if "models" in rep else ""
    print(
        f"{args.release}: valid BagIt bag, {rep['files']} payload files ({rep['bytes'] / 1e6:.1f} MB), every "
        f"sha256 matches{store} ({rep['seconds']:.1f} s)"
    )
    return 0


def _deposit(args: argparse.Namespace) -> int:
    from spinecohort.release import make_deposit

    for p in make_deposit(args.release, args.out):
        print(f"{p}  {p.stat().st_size / 1e6:.1f} MB")
    return 0


def _unpack(args: argparse.Namespace) -> int:
    from spinecohort.release import STORE_ZIP, safe_extract

    src = Path(args.release) / "data" / STORE_ZIP
    if not src.is_file():
        raise ValueError(f"{src} does not exist; is {args.release} a spinecohort release?")
    dest = (args.to or Path.cwd()) / "cohort.zarr"  # outside the bag by default: `verify` fails on extra files
    if dest.exists():
        raise ValueError(f"{dest} already exists; remove it or choose another --to")
    safe_extract(src, dest)
    print(dest)
    return 0


def _check_store(args: argparse.Namespace) -> int:
    from spinecohort.store.zarr_store import invalidate_shard, shard_problems

    problems = shard_problems(args.store)
    if not problems:
        print(f"{args.store}: every shard matches its recorded crc32c")
        return 0
    for shard, why in sorted(problems.items()):
        print(f"shard {shard:05d}: {why}")
    if not args.rebuild:
        print(
            f"{len(problems)} shard(s) to rebuild: run `spinecohort check-store {args.store} --rebuild`, then "
            "snakemake, which rewrites exactly those shards",
            file=sys.stderr,
        )
        return 1
    results = Layout(Path(args.store).parent)
    records = args.records or Path(results.path("shards"))
    for shard in sorted(problems):
        invalidate_shard(args.store, shard)
        for f in sorted(Path(records).glob(f"{shard:05d}.*")):  # sample record, quality, parameters
            f.unlink()
    # the store-wide check (results/store_check.csv) is stale too; without it Snakemake sees the missing
    # shard records as removed intermediates and would not rerun them
    Path(results.store_check).unlink(missing_ok=True)
    print(f"invalidated {len(problems)} shard(s) and their records in {records}: run snakemake to rebuild them")
    return 0


def _rom_table(args: argparse.Namespace) -> int:
    import pandas as pd

    from spinecohort.rom.tables import modes_markdown, sensitivity_markdown

    default = {"sensitivity": "results/rom/sensitivity.csv", "modes": "results/rom/modes.csv"}[args.table]
    path = Path(args.csv or default)
    if not path.is_file():
        raise ValueError(f"{path}: no such file (make it with: snakemake -j2 {default})")
    table = pd.read_csv(path)
    print((sensitivity_markdown if args.table == "sensitivity" else modes_markdown)(table), end="")
    return 0


def _query(args: argparse.Namespace) -> int:
    import pandas as pd

    from spinecohort.measure.tables import parse_range, query_models

    filters = args.filters
    if len(filters) % 2 or not all(f.startswith("--") for f in filters[::2]):
        raise ValueError(f"query filters must be pairs '--PARAM lo:hi', got {' '.join(filters)}")
    ranges = {k[2:]: parse_range(v, k[2:]) for k, v in zip(filters[::2], filters[1::2])}
    layout = Layout(args.results) if args.results else _config_and_layout(args)[1]  # --results needs no config
    csv = Path(layout.virtual_cohort_csv)
    if not csv.is_file():
        raise ValueError(f"{csv} does not exist; run the pipeline (snakemake) first")
    ids = query_models(pd.read_csv(csv), ranges)
    print("\n".join(ids))
    print(f"{len(ids)} models match", file=sys.stderr)
    return 0


def _personalize(args: argparse.Namespace) -> int:
    from spinecohort.cohort.landmarks import Landmarks
    from spinecohort.measure.spinopelvic import UNITS
    from spinecohort.personalize.cohort import Settings, build_model, personalized_hex
    from spinecohort.personalize.parameters import complete_pelvic_targets
    from spinecohort.ssm.model import SSM

    filters = args.filters
    if not filters or len(filters) % 2 or not all(f.startswith("--") for f in filters[::2]):
        raise ValueError(
            f"personalize needs target pairs '--PARAM value', e.g. --PI 55 --PT 28 --LL 30, got '{' '.join(filters)}'"
        )
    targets = {}
    for k, v in zip(filters[::2], filters[1::2]):
        try:
            targets[k[2:]] = float(v)
        except ValueError:
            raise ValueError(f"target {k} must be a number (deg / mm), got '{v}'") from None
    targets = complete_pelvic_targets(targets, source="command line")
    cfg, layout = _config_and_layout(args)
    settings = Settings.from_config(cfg["personalize"], cfg["grid"]["n_modes"])
    settings.parameters += [p for p in targets if p not in settings.parameters]  # weight 1 per deg / mm
    m = cfg["measure"]
    for f in (Path(layout.ssm), Path(layout.cohort)):
        if not f.is_file():
            raise ValueError(f"{f} does not exist; run the pipeline (snakemake) up to the SSM first")
    model = build_model(
        SSM.load(layout.ssm),
        Landmarks.from_cohort(layout.cohort),
        settings,
        {"vertical": m["vertical_axis"], "c7_proxy": m["c7_proxy"]},
    )
    res = model.fit(targets)
    print(
        f"weights (SD): {np.round(res.weights, 4).tolist()}; posture {res.posture_deg:.3f} deg; "
        f"{res.at_bound} weight(s) at +-{settings.bound_sd:g} SD"
    )
    print(f"{'parameter':<12}{'target':>10}{'achieved':>10}{'error':>9}  unit")
    for p in settings.parameters:
        t = targets.get(p, float("nan"))
        print(f"{p:<12}{t:>10.3f}{res.achieved[p]:>10.3f}{res.achieved[p] - t:>9.3f}  {UNITS.get(p, '')}")
    if args.out:
        from spinecohort.fe.export import NOT_ANATOMY, fe_model, write_deck
        from spinecohort.fe.materials import materials_from_config
        from spinecohort.fe.writers import write_vtu
        from spinecohort.mesh.hex_ssm import HexSSM
        from spinecohort.mesh.template import HexTemplate

        template = HexTemplate.load(layout.template)
        pts, rep = personalized_hex(
            template,
            HexSSM.load(layout.hex_ssm),
            res.weights,
            res.posture_deg,
            name="personalized model",
        )
        heading = (
            f"spinecohort personalized model: targets {targets}, weights (SD) "
            f"{np.round(res.weights, 4).tolist()}, posture {res.posture_deg:.3f} deg"
        )
        fe = fe_model(
            template,
            pts,
            hex_type=cfg["template"]["hex_type"],
            heading=heading,
            materials=materials_from_config(cfg.get("fe")),
        )
        if args.out.suffix == ".vtu":
            write_vtu(fe, args.out, leave_out=NOT_ANATOMY)  # a picture: no connector lines
        elif args.out.suffix == ".inp":
            write_deck(fe, args.out, provenance=heading)
        else:
            raise ValueError(f"--out {args.out}: use a .inp or .vtu file name")
        print(f"-> {args.out}; Jacobian check: {_scalars(rep)}")
    return 0


def _serve(args: argparse.Namespace) -> int:
    import time

    from spinecohort.web.data import open_data
    from spinecohort.web.launcher import Settings, bind, serve

    t0 = time.perf_counter()
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(
            f"spinecohort serve: WARNING: listening on {args.host} exposes the platform to every machine that can "
            "reach this one: anyone there can browse the data and make the server build and send models (no login, "
            "no encryption). Use it only on a trusted network, or keep the default 127.0.0.1 and tunnel (ssh -L).",
            file=sys.stderr,
        )
    if args.max_sessions < 1 or args.idle_timeout <= 0 or args.max_zip < 1:
        raise ValueError("--max-sessions, --idle-timeout and --max-zip must be positive")
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s spinecohort serve: %(message)s", "%H:%M:%S"))
    for name in ("spinecohort.serve", "spinecohort.web"):
        logging.getLogger(name).addHandler(handler)
        logging.getLogger(name).setLevel(logging.INFO)
        logging.getLogger(name).propagate = False
    sock = bind(args.host, args.port)  # a port in use is refused before the data are read
    if args.release and _is_url(args.release):  # the table and model inputs fetched once, models on demand
        from spinecohort.release.remote import RemoteRelease, platform_model_points

        remote = RemoteRelease(args.release, cache_dir=args.cache_dir, cache_mb=args.cache_mb)
        data = open_data(release=remote.platform_folder())
        data.model_points = platform_model_points(data, remote)
    else:
        data = open_data(results=args.results, release=args.release, config=args.config)
    for m in data.missing:
        print(f"spinecohort serve: not available: {m}", file=sys.stderr)
    settings = Settings(
        host=args.host,
        port=args.port,
        max_sessions=args.max_sessions,
        idle_timeout_s=60.0 * args.idle_timeout,
        max_zip=args.max_zip,
        public_hosts=tuple(args.public_host or ()),
    )
    print(
        f"serving {len(data.table):,} models from {data.src.origin} on http://{args.host}:{args.port}/ "
        f"to at most {args.max_sessions} browser sessions, each ending {args.idle_timeout:g} min after its last "
        f"action (data loaded in {time.perf_counter() - t0:.1f} s; Ctrl-C stops)",
        flush=True,
    )
    serve(data, settings, sock)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spinecohort", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate-cohort", help="write a synthetic patient cohort (STL folder + sheet + landmarks)")
    g.add_argument("out", type=Path)
    g.add_argument("--n", type=int, default=42, help="number of patients (default 42)")
    g.add_argument("--seed", type=int, default=20240549)
    g.add_argument("--resolution", choices=["coarse", "default", "fine"], default="default")
    g.add_argument("--noise-mm", type=float, default=0.8)
    g.add_argument("--quiet", action="store_true")
    g.set_defaults(func=_generate)

    w = sub.add_parser(
        "write-cohort-folder",
        help="write the synthetic cohort as a user brings one: every bone re-triangulated and shuffled, no landmarks",
    )
    w.add_argument("out", type=Path)
    w.add_argument(
        "--per-bone", action="store_true", help="one folder per patient, one file per bone (vertebrae_L3.stl)"
    )
    w.add_argument("--n", type=int, default=8, help="number of patients (default 8)")
    w.add_argument("--seed", type=int, default=20240549)
    w.add_argument(
        "--generator",
        choices=["real", "primitives"],
        default="real",
        help="real bones (default; register them with register.reference: real) or primitives (register.reference: "
        "synthetic)",
    )
    w.add_argument("--resolution", choices=["coarse", "default", "fine"], default="coarse", help="(primitives)")
    w.add_argument("--noise-mm", type=float, default=0.8, help="(primitives)")
    w.add_argument("--remesh-seed", type=int, default=0, help="seed of the re-triangulation and shuffling")
    w.set_defaults(func=_write_folder)

    c = sub.add_parser("check-cohort", help="validate a folder of patient STLs in correspondence")
    c.add_argument("folder", type=Path)
    c.add_argument("--sheet", type=Path)
    c.add_argument("--landmarks", type=Path)
    c.add_argument("--units", choices=["mm", "cm", "m"], default="mm")
    c.set_defaults(func=_check)

    s = sub.add_parser("ssm-info", help="summarise an ssm.npz (modes, compactness)")
    s.add_argument("ssm", type=Path)
    s.set_defaults(func=_ssm_info)

    e = sub.add_parser("export", help="materialize one virtual model (.inp, .stl or .vtu)")
    e.add_argument("model_id", help="model_08403 or 8403")
    e.add_argument("--format", choices=["inp", "stl", "vtu"], default="inp")
    e.add_argument("--out", type=Path)
    _add_config_args(e)
    e.add_argument(
        "--release",
        help="build from a release instead of the results: the bag folder, or its http(s) URL (the bag, the "
        "deposit, or its cohort.zarr.zip; the model's stored coordinates are read in place); needs neither "
        "config nor Snakemake",
    )
    e.add_argument("--cache-dir", type=Path, help="(--release URL) where fetched files go (default ~/.cache)")
    e.add_argument(
        "--load",
        choices=["flexion", "extension", "lateral_left", "lateral_right", "axial_left", "axial_right"],
        help="(inp) add a pure-moment step: pelvis fixed, the moment on --top through a rigid body; solve the "
        "deck with `ccx -i <name without .inp>` (docs/reference/deck.md)",
    )
    e.add_argument("--moment-nm", type=float, default=7.5, help="pure moment of --load in N.m (default 7.5)")
    e.add_argument("--top", default="T1", help="the loaded vertebra of --load (T1 ... L5, default T1)")
    e.add_argument(
        "--guided",
        action="store_true",
        help="(--load) the top turns about the load's axis only, as in the validation's lumbar model; the whole "
        "spine's extension reaches the full moment guided, while free it stalls (docs/explanation/fe-model.md)",
    )
    e.set_defaults(func=_export)

    v = sub.add_parser(
        "verify",
        help="check a release bag (or a downloaded deposit): every checksum, no missing or extra file, and "
        "every shard of the store zip intact",
    )
    v.add_argument("release", type=Path, help="the bag folder (results/release) or the deposit's folder")
    v.add_argument("--no-store", action="store_true", help="only the BagIt checks (not the store's shards)")
    v.add_argument("--tmpdir", type=Path, help="(deposit) where bag.zip is unpacked for the check")
    v.add_argument("--processes", type=int, default=1, help="hashing processes (default 1)")
    v.set_defaults(func=_verify)

    d = sub.add_parser(
        "deposit",
        help="the bag as the flat file list a repository takes: cohort.zarr.zip, bag.zip, README.md in OUT",
    )
    d.add_argument("release", type=Path, help="the bag folder (results/release)")
    d.add_argument("out", type=Path, help="folder for the deposit's files (the store zip is hard-linked)")
    d.set_defaults(func=_deposit)

    u = sub.add_parser(
        "unpack", help="unpack a release's store zip into DIR/cohort.zarr (checked: no member may leave DIR)"
    )
    u.add_argument("release", type=Path, help="the bag folder")
    u.add_argument("--to", type=Path, help="destination folder (default: the current one)")
    u.set_defaults(func=_unpack)

    pz = sub.add_parser(
        "personalize",
        help="a model fitted to spinopelvic parameters, e.g. personalize --PI 55 "
        "--PT 28 --LL 30 [--out model.inp] (deg / mm; any measured parameter)",
    )
    pz.add_argument("--out", type=Path, help="write the hex FE model (.inp or .vtu), Jacobian-checked and repaired")
    _add_config_args(pz)
    pz.set_defaults(func=_personalize)

    cs = sub.add_parser(
        "check-store",
        help="check every shard of a cohort store against its recorded size and crc32c; "
        "--rebuild invalidates bad shards so that snakemake rewrites them",
    )
    cs.add_argument("store", type=Path, help="the store (results/cohort.zarr)")
    cs.add_argument("--rebuild", action="store_true", help="remove bad shards and their per-shard records")
    cs.add_argument("--records", type=Path, help="per-shard records folder (default: <store>/../shards)")
    cs.set_defaults(func=_check_store)

    rt = sub.add_parser(
        "rom-table",
        help="the ROM sensitivity or mode-study table as Markdown, from results/rom/sensitivity.csv or modes.csv",
    )
    rt.add_argument("table", choices=["sensitivity", "modes"])
    rt.add_argument("csv", nargs="?", help="the rule's CSV (default results/rom/<table>.csv)")
    rt.set_defaults(func=_rom_table)

    q = sub.add_parser(
        "query",
        help="model IDs of the virtual cohort with parameters in ranges, "
        "e.g. query --PI 50:60 --PT 25: (bounds inclusive, deg / mm)",
    )
    _add_config_args(q)
    q.set_defaults(func=_query)

    sv = sub.add_parser(
        "serve",
        help="the cohort platform in the browser: filter, find a patient's model, see it in 3D, download "
        "(read-only; binds 127.0.0.1 unless --host says otherwise)",
    )
    _add_config_args(sv)
    sv.add_argument(
        "--release",
        help="serve a release instead: the bag folder (read in place, never written) or its http(s) URL (the "
        "table and model inputs fetched once, models read on demand)",
    )
    sv.add_argument("--cache-dir", type=Path, help="(--release URL) the cache folder (default ~/.cache/spinecohort)")
    sv.add_argument("--cache-mb", type=float, default=500.0, help="(--release URL) bound on cached models, MB")
    sv.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    sv.add_argument("--port", type=int, default=8080)
    sv.add_argument("--max-zip", type=int, default=25, help="most decks in one zip download (default 25)")
    sv.add_argument(
        "--max-sessions", type=int, default=8, help="most browser sessions at once (default 8; each is a process)"
    )
    sv.add_argument(
        "--idle-timeout",
        type=float,
        default=30.0,
        help="minutes without an action after which a session ends (default 30)",
    )
    sv.add_argument(
        "--public-host",
        action="append",
        help="a host name users type to reach this server (repeatable; loopback names are always accepted)",
    )
    sv.set_defaults(func=_serve)

    args, extra = parser.parse_known_args(argv)
    if extra and args.command not in ("query", "personalize"):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.filters = extra
    logging.basicConfig(level=logging.WARNING)
    try:
        return args.func(args)
    except ValueError as exc:  # input errors carry the file and the problem: print them, not a traceback
        print(f"spinecohort: error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:  # a results file not made yet, or a wrong --results / --config
        print(
            f"spinecohort: error: {exc.filename or exc}: no such file (the pipeline's files are made by "
            "`snakemake -j2`; --results and --config say where they are)",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
