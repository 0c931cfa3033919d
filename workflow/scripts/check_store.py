# Adapter: every shard of the store against its recorded size and crc32c; a table of the result, or a clear failure
# naming the bad shards and how to rebuild them.
from pathlib import Path

import pandas as pd

from spinecohort.logs import to_file
from spinecohort.store.zarr_store import shard_problems

with to_file(snakemake.log[0]) as log:
    store = Path(snakemake.input.store).parent
    problems = shard_problems(store)
    shards = [int(Path(r).name.split(".")[0]) for r in snakemake.input.records]
    table = pd.DataFrame(
        {"shard": shards, "ok": [s not in problems for s in shards], "problem": [problems.get(s, "") for s in shards]}
    )
    if problems:
        lines = "; ".join(f"shard {s:05d}: {why}" for s, why in sorted(problems.items()))
        raise RuntimeError(
            f"{store}: {len(problems)} shard(s) fail their checksum: {lines}. Run "
            f"`spinecohort check-store {store} --rebuild`, then snakemake again: it rewrites exactly "
            "those shards."
        )
    table.to_csv(snakemake.output[0], index=False)
    log.info("%s: all %d shards match their recorded crc32c", store, len(shards))
