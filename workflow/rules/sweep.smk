# Stage 3: the case table of each scenario (design of experiments).


rule sweep:
    input:
        meshes=lambda wc: [P.mesh(g) for g in PLAN.scenario_geometries(wc.scenario)],
        features=lambda wc: [P.features(g) for g in PLAN.scenario_geometries(wc.scenario)],
    output:
        cases=P.cases(),
        report=P.sweep_report(),
    params:
        sweep=lambda wc: PLAN.sweep_params(wc.scenario),
    log:
        P.log("sweep", "{scenario}"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/sweep.py"
