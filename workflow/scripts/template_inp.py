# Adapter: the Abaqus/CalculiX deck of the morphed mean, "Mean_Model (Template).inp".
import numpy as np

from spinecohort.fe.export import fe_model, write_deck
from spinecohort.fe.materials import materials_from_config
from spinecohort.logs import to_file
from spinecohort.mesh.template import HexTemplate

with to_file(snakemake.log[0]):
    template = HexTemplate.load(snakemake.input.template)
    with np.load(snakemake.input.nodes) as z:
        nodes = z["nodes"]
    model = fe_model(
        template,
        nodes,
        hex_type=snakemake.params.hex_type,
        heading="spinecohort mean model (template)",
        materials=materials_from_config(snakemake.params.fe),
    )
    write_deck(model, snakemake.output[0], provenance="mean of the SSM, morphed hex template")
