# Stage 2: tetrahedral mesh + boundary regions + geometric features.


rule mesh:
    input:
        surface=P.surface(),
        # an imported liver's own files, read again here: the liver (as given, vertex ids, groups), its
        # supports' and exertion points' point files; editing one re-runs the mesh and what follows
        files=lambda wc: PLAN.geometry_files(wc.gid, stage="mesh"),
    output:
        mesh=P.mesh(),
        features=P.features(),
        picture=P.regions_picture(),
    params:
        mesh=config_slice("mesh"),
        seed=lambda wc: PLAN.seed("mesh", wc.gid),
        exertion=config_slice("sweep", "exertion"),
    log:
        P.log("mesh", "{gid}"),
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
        [P.mesh(g) for g in PLAN.all_geometries],
