# Stage 1: a closed liver surface per geometry id (procedural, cube, imported).


rule geometry:
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
