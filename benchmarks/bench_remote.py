"""Reading the release over HTTP: time to first model and bytes sent for cold reads, from a local nginx.

    .venv/bin/python benchmarks/bench_remote.py --release results/release          # the built release bag
    .venv/bin/python benchmarks/bench_remote.py --store DIR/cohort.zarr --work DIR  # a store: zipped first
    .venv/bin/python benchmarks/bench_remote.py --chunking DIR/c1/cohort.zarr DIR/c7/cohort.zarr ...

nginx (scripts/install_system_deps.sh) serves the release's ``data/`` on 127.0.0.1; its access log gives the
bytes sent per request.  Printed: the time to open the store and read a first model (a new reader, nothing
cached), then 10 random models of the written shards, each read cold (a new reader each), with bytes per
model against the goal (at most twice the model's own compressed bytes plus the shard indexes) and what a
50 Mbit/s link would wait for those bytes.  A store given with --store may hold only some of its shards
(the others read as never written): the per-shard layout, and so the bytes of a model read, is the full
store's.  --chunking: bytes per node and bytes sent per model read for stores that differ in chunk_models
(each served as a folder: the same byte ranges as the zip), and --layouts compares how readers fare on the
zip (zarr-python with the references; tensorstore's zip driver) against the shard objects as flat files.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from spinecohort.release import STORE_REFS, STORE_ZIP, open_store, read_model_from, write_references
from spinecohort.release.archive import write_store_zip
from spinecohort.release.nginx import LocalServer
from spinecohort.release.reader import surface_vertex

LINK_BITS_PER_S = 50e6
#: largest store zip on which --layouts runs tensorstore's zip driver (it fetches whole members)
TENSORSTORE_MAX_BYTES = 200e6


def written_models(store_attrs: dict, keys) -> np.ndarray:
    """Model IDs of the shards whose checksum record is among the store's keys (the written shards)."""
    sm, n = int(store_attrs["shard_models"]), int(store_attrs["n_models"])
    shards = [s for s in range(int(store_attrs["n_shards"])) if f"checksums/shard_{s:05d}/zarr.json" in keys]
    return np.concatenate([np.arange(s * sm, min((s + 1) * sm, n)) for s in shards])


def own_bytes(zip_path: Path, refs: dict, attrs: dict, model: int) -> tuple[float, int]:
    """(the model's own compressed bytes: its chunk's bytes / models per chunk, summed over both point arrays;
    the two shard indexes' bytes), read from the zip's shard indexes."""
    shard, row = divmod(model, int(attrs["shard_models"]))
    n_chunks = int(attrs["shard_models"]) // int(attrs["chunk_models"])
    own, index = 0.0, 0
    with open(zip_path, "rb") as f:
        for name in ("tri/points", "hex/volume_points"):
            _, off, size = refs[f"{name}/c/{shard}/0/0"]
            n_index = 16 * n_chunks + 4
            f.seek(off + size - n_index)
            table = np.frombuffer(f.read(n_index)[:-4], "<u8").reshape(-1, 2)
            own += table[row // int(attrs["chunk_models"]), 1] / int(attrs["chunk_models"])
            index += n_index
    return own, index


def cold_read(url: str, model: int, srv: LocalServer) -> dict:
    """Open the store anew and read one model; seconds and bytes sent (access log) for each phase."""
    srv.clear_log()
    t0 = time.perf_counter()
    root = open_store(url)
    skin = surface_vertex(root)
    t_open = time.perf_counter()
    opened = srv.requests()  # the probe, the references, the skin's chunk (nginx logs a request once sent)
    read_model_from(root, model, skin)
    t_read = time.perf_counter()
    sent = srv.requests()
    return {
        "open_s": t_open - t0,
        "read_s": t_read - t_open,
        "bytes": sum(r.nbytes for r in sent),
        "requests": len(sent),
        "open_bytes": sum(r.nbytes for r in opened),
    }


def bench_release(data: Path, work: Path, n_random: int, seed: int) -> None:
    zip_path = data / STORE_ZIP
    refs = json.loads((data / STORE_REFS).read_text())["refs"]
    with LocalServer(data, work / "nginx") as srv:
        url = f"{srv.url}/{STORE_ZIP}"
        root = open_store(url)
        attrs = dict(root.attrs)
        ids = written_models(attrs, set(refs))
        print(
            f"store {zip_path} ({zip_path.stat().st_size / 1e9:.2f} GB): {attrs['n_models']} models, shards of "
            f"{attrs['shard_models']}, {attrs['chunk_models']} model(s) per chunk; {len(ids)} models written"
        )
        rng = np.random.default_rng(seed)
        picks = [int(attrs.get("n_models", 1) // 2) if int(attrs["n_models"]) // 2 in ids else int(ids[0])]
        picks += [int(i) for i in rng.choice(ids, n_random, replace=False)]
        rows = []
        for k, i in enumerate(picks):
            r = cold_read(url, i, srv)
            own, index = own_bytes(zip_path, refs, attrs, i)
            r.update(model=i, own=own, index=index, model_bytes=r["bytes"] - r["open_bytes"])
            rows.append(r)
            tag = "first" if k == 0 else f"random {k:2d}"
            print(
                f"  {tag}: model_{i:05d}  open {r['open_s']:.3f} s + read {r['read_s']:.3f} s; "
                f"{r['requests']} requests, {r['bytes'] / 1e6:.3f} MB sent ({r['open_bytes'] / 1e3:.1f} kB to open); "
                f"model {r['model_bytes'] / 1e6:.3f} MB vs bound 2 x {own / 1e6:.3f} + {index / 1e6:.3f} MB"
            )
        first, rand = rows[0], rows[1:]
        per_model_s = np.array([r["open_s"] + r["read_s"] for r in rand])
        per_model_b = np.array([r["bytes"] for r in rand])
        ok_bytes = all(r["model_bytes"] <= 2 * r["own"] + r["index"] for r in rows)
        print(
            f"time to first model: {first['open_s'] + first['read_s']:.3f} s, {first['bytes'] / 1e6:.3f} MB "
            f"(50 Mbit/s: {first['bytes'] * 8 / LINK_BITS_PER_S:.2f} s of transfer)"
        )
        print(
            f"{len(rand)} random models, each cold: {per_model_s.mean():.3f} s mean, {per_model_s.max():.3f} s max; "
            f"{per_model_b.sum() / 1e6:.2f} MB in all, {per_model_b.mean() / 1e6:.3f} MB per model "
            f"(50 Mbit/s: {per_model_b.sum() * 8 / LINK_BITS_PER_S:.1f} s, {per_model_b.mean() * 8 / LINK_BITS_PER_S:.2f} s per model)"
        )
        print(
            f"goal <= 1 s per model: {'met' if per_model_s.max() <= 1.0 else 'MISSED'}; "
            f"bytes <= 2 x own + shard index: {'met' if ok_bytes else 'MISSED'} "
            f"(mean own {np.mean([r['own'] for r in rows]) / 1e6:.3f} MB, index {rows[0]['index'] / 1e6:.3f} MB)"
        )


def bench_chunking(stores: list[Path], work: Path, n_random: int, seed: int) -> None:
    """Bytes per node and bytes sent per cold model read, per chunk_models (stores served as folders)."""
    import zarr

    print(
        f"{'chunk_models':>12s} {'B/node':>7s} {'own MB':>7s} {'index MB':>8s} {'sent MB':>8s} {'sent/own':>8s} {'s/model':>8s}"
    )
    for store in stores:
        z = zarr.open_group(str(store), mode="r")
        attrs = dict(z.attrs)
        ids = written_models(attrs, {p.relative_to(store).as_posix() for p in store.glob("checksums/*/zarr.json")})
        n_nodes = z["tri/points"].shape[1] + int(attrs["n_hex_nodes"])
        shards = {int(s[6:]) for s in z["checksums"].group_keys()}
        nbytes = sum(rec["bytes"] for s in shards for rec in z["checksums"][f"shard_{s:05d}"].attrs["objects"].values())
        b_node = nbytes / (len(ids) * n_nodes)
        with LocalServer(store.parent, work / f"nginx-{store.parent.name}") as srv:
            url = f"{srv.url}/{store.name}"
            rng = np.random.default_rng(seed)
            sent, secs, own_all, index = [], [], [], 0
            for i in rng.choice(ids, n_random, replace=False):
                root = zarr.open_group(url, mode="r")  # a folder over HTTP: the same ranges as the zip
                srv.clear_log()
                t0 = time.perf_counter()
                root["tri/points"][int(i)]
                root["hex/volume_points"][int(i)]
                secs.append(time.perf_counter() - t0)
                sent.append(sum(r.nbytes for r in srv.requests()))
                shard, row = divmod(int(i), int(attrs["shard_models"]))
                own = 0.0
                cm = int(attrs["chunk_models"])
                n_chunks = int(attrs["shard_models"]) // cm
                for name in ("tri/points", "hex/volume_points"):
                    obj = store / name / "c" / str(shard) / "0" / "0"
                    with open(obj, "rb") as f:
                        f.seek(-(16 * n_chunks + 4), 2)
                        table = np.frombuffer(f.read()[:-4], "<u8").reshape(-1, 2)
                    own += table[row // cm, 1] / cm
                index = 2 * (16 * n_chunks + 4)
                own_all.append(own)
        print(
            f"{attrs['chunk_models']:>12d} {b_node:7.3f} {np.mean(own_all) / 1e6:7.3f} {index / 1e6:8.3f} "
            f"{np.mean(sent) / 1e6:8.3f} {np.mean(sent) / np.mean(own_all):8.2f} {np.mean(secs):8.3f}"
        )


def bench_layouts(data: Path, work: Path, model: int) -> None:
    """Bytes sent for one model by: zarr-python with the references (exact ranges), tensorstore's zip
    driver over HTTP, and the shard objects as flat files (a folder store over HTTP)."""
    import tensorstore as ts

    with LocalServer(data, work / "nginx-layouts") as srv:
        url = f"{srv.url}/{STORE_ZIP}"
        r = cold_read(url, model, srv)
        print(f"zip + references (zarr-python): {r['bytes'] / 1e6:10.3f} MB in {r['requests']} requests")
        size = (data / STORE_ZIP).stat().st_size
        if size > TENSORSTORE_MAX_BYTES:  # its zip driver reads whole members: GBs, and it stalls on them here
            print(
                f"zip, tensorstore zip kvstore: skipped ({size / 1e9:.1f} GB zip; it would fetch whole shard objects)"
            )
            return
        srv.clear_log()
        t0 = time.perf_counter()
        for name in ("tri/points", "hex/volume_points"):
            spec = {"driver": "zarr3", "kvstore": {"driver": "zip", "base": url, "path": f"{name}/"}}
            ts.open(spec, read=True).result()[model].read().result()
        sent = srv.requests()
        print(
            f"zip, tensorstore zip kvstore:  {sum(q.nbytes for q in sent) / 1e6:10.3f} MB in {len(sent)} requests "
            f"({time.perf_counter() - t0:.1f} s: it reads whole members, i.e. whole shard objects)"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--release", type=Path, help="a release bag (its data/ is served)")
    ap.add_argument("--store", type=Path, help="a store folder: zipped (with references) into --work first")
    ap.add_argument("--work", type=Path, help="scratch folder (default: a temporary one)")
    ap.add_argument("--chunking", type=Path, nargs="*", help="store folders differing in chunk_models")
    ap.add_argument("--layouts", action="store_true", help="also compare readers on the zip (one model)")
    ap.add_argument("--models", type=int, default=10, help="random models to read (default 10)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-remote-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        if args.chunking:
            bench_chunking(args.chunking, work, args.models, args.seed)
        data = args.release / "data" if args.release else None
        if args.store:
            data = work / "data"
            data.mkdir(exist_ok=True)
            if not (data / STORE_ZIP).is_file():
                t0 = time.perf_counter()
                z = write_store_zip(data / STORE_ZIP, args.store)
                write_references(data / STORE_REFS, data / STORE_ZIP)
                print(f"zipped {args.store}: {z['bytes'] / 1e9:.2f} GB in {time.perf_counter() - t0:.0f} s")
        if data is not None:
            bench_release(data, work, args.models, args.seed)
            if args.layouts:
                bench_layouts(data, work, 0)


if __name__ == "__main__":
    main()
