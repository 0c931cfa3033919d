# Adapter: the model's ROM against the in-vitro references (table + the seed's Figures 10-11 as one figure),
# the physiological orderings of its lumbar segments and the ALL effect.
import pandas as pd

from spinecohort.figures.rom import validation_figure
from spinecohort.logs import to_file
from spinecohort.rom.compare import all_effect, orderings, validate_from_config, validation_markdown

with to_file(snakemake.log[0]) as log:
    table = pd.read_csv(snakemake.input[0])
    val = validate_from_config(table, snakemake.params.rom)
    val.to_csv(snakemake.output.table, index=False)
    with open(snakemake.output.markdown, "w") as f:
        f.write(validation_markdown(val))
    all_effect(table).to_csv(snakemake.output.all_effect, index=False)
    order = orderings(table, mode="lumbar" if (table["mode"] == "lumbar").any() else "unit")
    order.to_csv(snakemake.output.orderings, index=False)
    validation_figure(val, snakemake.output.figure, title=snakemake.params.model)
    cols = ["segment", "motion", "side", "mode", "model_deg", "criterion", "accept_low", "accept_high", "in_range"]
    log.info(
        "validation: %d of %d in range (seed criterion: %d)\n%s\norderings:\n%s",
        int((val["in_range"] == True).sum()),  # noqa: E712 (None = not judged)
        len(val),
        int((val["in_range_seed"] == True).sum()),  # noqa: E712
        val[cols + ["in_range_seed"]].to_string(),
        order.to_string(),
    )
