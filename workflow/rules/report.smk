# Stage 8: one human-readable summary of the run.


rule report:
    input:
        models=expand(f"{E}/models/{{scenario}}/{{variant}}/metrics.json", scenario=PLAN.train_scenarios(), variant=list(PLAN.variants())),
        manifests=expand(f"{E}/shards/{{scenario}}/manifest.json", scenario=PLAN.all_scenarios()),
        validation=f"{E}/validate/metrics.json",
        features=expand(f"{E}/mesh/{{gid}}.features.json", gid=PLAN.all_geometries),
        pictures=expand(f"{E}/mesh/{{gid}}.regions.png", gid=PLAN.all_geometries),
    output:
        html=f"{E}/report/index.html",
    params:
        report=config_slice("report"),
        experiment=config_slice("experiment"),
    log:
        f"{E}/logs/report/report.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/report.py"
