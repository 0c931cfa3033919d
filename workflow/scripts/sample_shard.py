# Adapter: sample one shard of the virtual cohort (tri + hex), check every hex, repair inverted models,
# write the shard to the store (its only writer), then the per-model quality table and the shard record.
import json
import time
from pathlib import Path

from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM
from spinecohort.store.shards import sample_shard
from spinecohort.store.zarr_store import shard_range, weights_of, write_shard

with to_file(snakemake.log[0]) as log:
    t0 = time.perf_counter()
    grid, settings = snakemake.params.grid, snakemake.params.settings
    shard = int(snakemake.wildcards.shard)
    total = len(grid["levels"]) ** grid["n_modes"]
    start, stop = shard_range(shard, settings["shard_models"], total)
    ids = list(range(start, stop))
    weights = weights_of(ids, grid["n_modes"], grid["levels"])
    tri, hexp, quality, timing = sample_shard(
        SSM.load(snakemake.input.ssm),
        HexSSM.load(snakemake.input.hex_ssm),
        HexTemplate.load(snakemake.input.template),
        weights,
        ids,
        repair=settings["repair"],
        log=log,
    )
    unrepaired = quality.loc[quality["invalid_after"] > 0]
    if len(unrepaired) and settings["fail_on_unrepaired"]:
        raise RuntimeError(
            f"shard {shard}: {len(unrepaired)} models keep inverted hexes after repair: "
            + "; ".join(unrepaired["repair_error"].astype(str).tolist()[:5])
        )
    t1 = time.perf_counter()
    record = write_shard(Path(snakemake.input.store).parent, shard, tri, hexp)
    wall = time.perf_counter() - t0
    quality.to_csv(snakemake.output.quality, index=False, float_format="%.6g")
    record.update(
        timing,
        write_s=time.perf_counter() - t1,
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
        "%.1f s (%.1f models/s)",
        shard,
        start,
        stop - 1,
        record["models_distracted"],
        record["models_inverted"],
        record["models_repaired"],
        len(unrepaired),
        wall,
        record["models_per_s"],
    )
