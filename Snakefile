# spinecohort: thoracolumbar spine SSM and virtual cohort of hexahedral FE models.
# The table of contents of the pipeline; every stage lives in workflow/rules/.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/register.smk"
include: "workflow/rules/cohort.smk"
include: "workflow/rules/ssm.smk"
include: "workflow/rules/measure.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/fe.smk"
include: "workflow/rules/store.smk"
include: "workflow/rules/personalize.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/rom.smk"
include: "workflow/rules/release.smk"  # last: its input function uses every stage's targets


rule all:
    default_target: True
    input:
        final_outputs(),
