# Stage 2: tetrahedral mesh + boundary regions + geometric features.


rule mesh:
    input:
        surface=f"{E}/geometry/{{gid}}.ply",
    output:
        mesh=f"{E}/mesh/{{gid}}.vtu",
        features=f"{E}/mesh/{{gid}}.features.json",
        picture=f"{E}/mesh/{{gid}}.regions.png",
    params:
        mesh=config_slice("mesh"),
        seed=config_slice("seed"),
        exertion=config_slice("sweep", "exertion"),
    log:
        f"{E}/logs/mesh/{{gid}}.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/mesh.py"


rule meshes:
    input:
        expand(f"{E}/mesh/{{gid}}.vtu", gid=PLAN.all_geometries),
