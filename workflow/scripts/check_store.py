# Adapter: every shard of the store against its recorded size and crc32c; a table of the result, or a clear failure
# naming the bad shards and how to rebuild them.
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.logs import to_file
from spinecohort.store.zarr_store import shard_problems

with to_file(snakemake.log[0]) as log:
    store = Path(snakemake.input.store).parent
    problems = shard_problems(store)
    shards = [int(Path(r).name.split(".")[0]) for r in snakemake.input.records]
    table = {
        "shard": np.array(shards, dtype=np.int64),
        "ok": np.array([s not in problems for s in shards]),
        "problem": np.array([problems.get(s, "") for s in shards], dtype=object),
    }
    if problems:
        lines = "; ".join(f"shard {s:05d}: {why}" for s, why in sorted(problems.items()))
        raise RuntimeError(
            f"{store}: {len(problems)} shard(s) fail their checksum: {lines}. Run "
            f"`spinecohort check-store {store} --rebuild`, then snakemake again: it rewrites exactly "
            "those shards."
        )
    pd.DataFrame(table).to_csv(snakemake.output[0], index=False, float_format="%g")
    log.info("%s: all %d shards match their recorded crc32c", store, len(shards))
