# Stage 3: the case table of each scenario (design of experiments).


rule sweep:
    input:
        meshes=lambda wc: expand(f"{E}/mesh/{{gid}}.vtu", gid=PLAN.scenario_geometries(wc.scenario)),
        features=lambda wc: expand(f"{E}/mesh/{{gid}}.features.json", gid=PLAN.scenario_geometries(wc.scenario)),
    output:
        cases=f"{E}/sweep/{{scenario}}/cases.parquet",
        report=f"{E}/sweep/{{scenario}}/sweep.json",
    params:
        sweep=lambda wc: PLAN.sweep_params(wc.scenario),
    log:
        f"{E}/logs/sweep/{{scenario}}.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/sweep.py"
