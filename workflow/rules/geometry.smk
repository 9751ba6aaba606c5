# Stage 1: a closed liver surface per geometry id (procedural, cube, imported).


rule geometry:
    input:
        # an imported liver's file (none for procedural livers): editing it re-runs this geometry and what
        # follows; a missing one stops Snakemake before any job (Plan.geometry_files)
        files=lambda wc: PLAN.geometry_files(wc.gid, stage="geometry"),
    output:
        surface=P.surface(),
        meta=P.surface_meta(),
    params:
        spec=lambda wc: PLAN.geometry_spec(wc.gid),
    log:
        P.log("geometry", "{gid}"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/geometry.py"
