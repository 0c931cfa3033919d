# Adapter: element quality of the morphed mean hex mesh and its Table 3 summary per tissue.
import numpy as np
import pandas as pd

from spinecohort.logs import to_file
from spinecohort.mesh.quality.table3 import hex_quality_metrics, table3_summary
from spinecohort.mesh.template import HexTemplate

with to_file(snakemake.log[0]) as log:
    template = HexTemplate.load(snakemake.input.template)
    with np.load(snakemake.input.nodes) as z:
        nodes = z["nodes"]
    metrics = hex_quality_metrics(nodes, template.hexes)
    part = template.part_of_hex()
    pd.DataFrame({"element": np.arange(len(part)), "tissue": part, **metrics}).to_csv(
        snakemake.output.elements, index=False, float_format="%.5g"
    )
    table = table3_summary(metrics, part)
    log.info("Table 3 of the morphed mean:\n%s", table.to_string(index=False))
    table.to_csv(snakemake.output.table3, index=False)
