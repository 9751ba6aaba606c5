# liverforce workflow: geometry -> mesh -> sweep -> simulate -> shards -> train -> validate + studies -> report
#
#   snakemake --cores 2                                   # default experiment
#   snakemake --cores 2 --config experiment=smoke         # another experiment
#   snakemake --cores 2 --config overrides="sweep.seed=3 mesh.target_nodes=4000"
#
# The configuration is composed once from config/ (Hydra) in common.smk; each
# rule receives only the slice it uses through `params:`.

include: "workflow/rules/common.smk"
include: "workflow/rules/geometry.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/sweep.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/validate.smk"
include: "workflow/rules/physics.smk"
include: "workflow/rules/study.smk"
include: "workflow/rules/report.smk"


rule all:
    default_target: True
    input:
        report=P.report(),
