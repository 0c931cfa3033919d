# Adapter: measure one shard read back from the store, on the triangulated and on the hex points.
from pathlib import Path

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.mesh.template import HexTemplate
from spinecohort.store.shards import hex_landmarks, measure_shard, shard_models_of
from spinecohort.store.zarr_store import read_shard

with to_file(snakemake.log[0]) as log:
    shard, path = int(snakemake.wildcards.shard), Path(snakemake.input.store).parent
    ids, weights = shard_models_of(path, shard)
    landmarks = load_cohort_npz(snakemake.input.cohort).landmarks
    hex_lm = hex_landmarks(HexTemplate.load(snakemake.input.template), landmarks)
    p = snakemake.params.measure
    params, diff = measure_shard(
        read_shard(path, shard, "tri/points"),
        read_shard(path, shard, "hex/points"),
        weights,
        ids,
        landmarks,
        hex_lm,
        vertical=p["vertical_axis"],
        assumed_age=p["assumed_age"],
        c7_proxy=p["c7_proxy"],
    )
    params.to_csv(snakemake.output.params, index=False, float_format="%.6f")
    diff.to_csv(snakemake.output.tri_vs_hex, index=False, float_format="%.6g")
    log.info(
        "shard %d: %d models measured; largest |tri - hex|: %s",
        shard,
        len(params),
        diff.nlargest(5, "max_abs_diff").round(4).to_dict("records"),
    )
