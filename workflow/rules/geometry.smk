# Stage 1: a closed liver surface per geometry id (procedural, cube, imported).


rule geometry:
    output:
        surface=f"{E}/geometry/{{gid}}.ply",
        meta=f"{E}/geometry/{{gid}}.json",
    params:
        spec=lambda wc: PLAN.geometry_spec(wc.gid),
    log:
        f"{E}/logs/geometry/{{gid}}.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/geometry.py"
