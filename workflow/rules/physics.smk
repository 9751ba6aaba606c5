# Stage 7b: what the modelling choices (supports, gravity, tool) cost every scenario-IV model, on one unseen liver.


rule physics:
    input:
        cases=P.cases(plan.VALIDATION),
        mesh=P.mesh(PLAN.scenario_geometries(plan.VALIDATION)[config_slice("validate", "physics", "liver")]),
        model=needs_iv("the physics check (rule physics)", [P.model_dir("IV", v) for v in PLAN.variants()]),
        metrics=[P.model_metrics("IV", v) for v in PLAN.variants()],
    output:
        study=P.physics(),
        shards=directory(P.physics_shards()),
    params:
        simulate=config_slice("simulate"),
        boundary=config_slice("boundary"),
        dataset=config_slice("dataset"),
        material=config_slice("material"),
        spec=PLAN.physics_spec(),  # validate.physics (+ the sphere's force scale on a lab liver of its own material)
    log:
        P.log("validate", "physics"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=30,
    script:
        "../scripts/physics.py"
