# Adapter: one patient's meshes (one file, or a folder of per-bone files) -> the reference registered onto it.
from spinecohort.cohort.register import LabeledReference, register_patient_files
from spinecohort.logs import to_file

with to_file(snakemake.log[0]):
    register_patient_files(
        LabeledReference.load(snakemake.input.reference),
        snakemake.input.patient,
        snakemake.wildcards.patient,
        layout=snakemake.params.layout,
        units=snakemake.params.units,
        params=snakemake.params.register,
        out_stl=snakemake.output.stl,
        out_report=snakemake.output.report,
    )
