# Adapter: the model's ROM against the in-vitro references (table + the seed's Figures 10-11 as one figure) and
# the physiological orderings of its lumbar segments; its nucleus pressures, facet forces,
# L1-L5 and same-geometry ROM against the packaged references (table, Markdown sections, figure).
import pandas as pd

from spinecohort.figures.rom import loads_figure, validation_figure
from spinecohort.logs import to_file
from spinecohort.rom import references
from spinecohort.rom.compare import orderings, validate_from_config, validation_markdown
from spinecohort.rom.outcomes import outcomes, outcomes_markdown

with to_file(snakemake.log[0]) as log:
    rom = snakemake.params.rom
    table = pd.read_csv(snakemake.input.table)
    idp, facets = pd.read_csv(snakemake.input.idp), pd.read_csv(snakemake.input.facets)
    val = validate_from_config(table, rom)
    val.to_csv(snakemake.output.table, index=False)
    references = {
        "intradiscal_pressure": references.intradiscal_pressure(),
        "facet_force": references.facet_forces(),
        "lumbar_total_rom": references.lumbar_total_rom(),
        "segmental_rom_same_geometry": pd.concat(
            [references.remus_segmental_rom(), references.in_vitro_segmental_rom()]
        ),
    }
    more = outcomes(table, idp, facets, references, rom["moment_nmm"], rom["acceptance_sd"])
    more.to_csv(snakemake.output.outcomes, index=False)
    with open(snakemake.output.markdown, "w") as f:
        f.write(validation_markdown(val) + "\n" + outcomes_markdown(more, idp, facets))
    order = orderings(table, mode="lumbar" if (table["mode"] == "lumbar").any() else "unit")
    order.to_csv(snakemake.output.orderings, index=False)
    validation_figure(val, snakemake.output.figure, title=snakemake.params.model)
    loads_figure(idp, facets, snakemake.output.loads_figure, title=snakemake.params.model)
    cols = ["segment", "motion", "side", "mode", "model_deg", "criterion", "accept_low", "accept_high", "in_range"]
    log.info(
        "validation: %d of %d in range (seed criterion: %d)\n%s\norderings:\n%s\nbeyond ROM:\n%s",
        int((val["in_range"] == True).sum()),  # noqa: E712 (None = not judged)
        len(val),
        int((val["in_range_seed"] == True).sum()),  # noqa: E712
        val[cols + ["in_range_seed"]].to_string(),
        order.to_string(),
        more.drop(columns=["source"]).to_string(),
    )
