# Adapter: one pass over one shard of the virtual cohort: sample (tri + hex), check every hex, repair
# inverted models, Table 3 rows, spinopelvic parameters (tri and hex), one streaming store write; then the
# per-shard tables and, last, the shard record (the job's completion mark).
import json
import time
from pathlib import Path

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM
from spinecohort.store.shards import DEFAULT_CHUNK, hex_landmarks, process_shard, shard_models_of
from spinecohort.store.zarr_store import ShardWriter

with to_file(snakemake.log[0]) as log:
    t0 = time.perf_counter()
    settings, p = snakemake.params.settings, snakemake.params.measure
    shard, store = int(snakemake.wildcards.shard), Path(snakemake.input.store).parent
    ids, weights = shard_models_of(store, shard)  # the store's own grid, not the config's
    template = HexTemplate.load(snakemake.input.template)
    landmarks = load_cohort_npz(snakemake.input.cohort).landmarks
    writer = ShardWriter(store, shard)
    batch = -(-DEFAULT_CHUNK // writer.chunk) * writer.chunk  # whole store chunks per batch
    t_load = time.perf_counter()
    try:
        quality, params, diff, timing = process_shard(
            SSM.load(snakemake.input.ssm),
            HexSSM.load(snakemake.input.hex_ssm),
            template,
            weights,
            ids,
            landmarks,
            hex_landmarks(template, landmarks),
            writer=writer,
            batch=batch,
            repair=settings["repair"],
            log=log,
            vertical=p["vertical_axis"],
            assumed_age=p["assumed_age"],
            c7_proxy=p["c7_proxy"],
        )
        unrepaired = quality.loc[quality["invalid_after"] > 0]
        if len(unrepaired) and settings["fail_on_unrepaired"]:
            raise RuntimeError(
                f"shard {shard}: {len(unrepaired)} models keep inverted hexes after repair: "
                + "; ".join(unrepaired["repair_error"].astype(str).tolist()[:5])
            )
    except BaseException:
        writer.abort()
        raise
    t1 = time.perf_counter()
    record = writer.close()
    quality.to_csv(snakemake.output.quality, index=False, float_format="%.6g")
    params.to_csv(snakemake.output.params, index=False, float_format="%.6f")
    diff.to_csv(snakemake.output.tri_vs_hex, index=False, float_format="%.6g")
    wall = time.perf_counter() - t0
    record.update(
        timing,
        load_s=t_load - t0,
        close_s=time.perf_counter() - t1,
        encode_cpu_s=writer.encode_cpu_s,
        stored_bytes=writer.stored_bytes,
        wall_s=wall,
        models_per_s=len(ids) / wall,
        models_inverted=int((quality["invalid_before"] > 0).sum()),
        models_distracted=int((quality.get("distraction_mm", 0) > 0).sum()),
        models_repaired=int(quality["repaired"].sum()),
        models_unrepaired=len(unrepaired),
    )
    with open(snakemake.output.record, "w") as fh:
        json.dump(record, fh, indent=1)
    log.info(
        "shard %d: models %d-%d, %d discs opened, %d with inverted hexes, %d repaired, %d unrepaired; "
        "%.1f s (%.1f models/s); largest |tri - hex|: %s",
        shard,
        ids[0],
        ids[-1],
        record["models_distracted"],
        record["models_inverted"],
        record["models_repaired"],
        len(unrepaired),
        wall,
        record["models_per_s"],
        diff.nlargest(3, "max_abs_diff").round(4).to_dict("records"),
    )
