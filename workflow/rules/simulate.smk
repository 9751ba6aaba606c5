# Stages 4-5: FE simulation of one shard of cases -> one Parquet shard; the manifest.
import math


rule simulate:
    input:
        cases=f"{E}/sweep/{{scenario}}/cases.parquet",
        meshes=lambda wc: expand(f"{E}/mesh/{{gid}}.vtu", gid=PLAN.scenario_geometries(wc.scenario)),
    output:
        shard=f"{E}/shards/{{scenario}}/shard-{{shard}}.parquet",
    params:
        simulate=config_slice("simulate"),
        boundary=config_slice("boundary"),
        dataset=config_slice("dataset"),
    log:
        f"{E}/logs/simulate/{{scenario}}-{{shard}}.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        # every case may use its whole time limit: the shard's worst case, more on each retry (SLURM --time, --mem)
        mem_mb=lambda wc, attempt: 4000 * attempt,
        runtime=lambda wc, attempt: attempt * (5 + math.ceil(
            config_slice("sweep", "cases_per_shard") * config_slice("simulate", "time_limit_s") / 60)),
    script:
        "../scripts/simulate.py"


rule manifest:
    input:
        shards=lambda wc: expand(f"{E}/shards/{{scenario}}/shard-{{shard}}.parquet", scenario=wc.scenario, shard=PLAN.shard_ids(wc.scenario)),
    output:
        manifest=f"{E}/shards/{{scenario}}/manifest.json",
    log:
        f"{E}/logs/manifest/{{scenario}}.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    script:
        "../scripts/manifest.py"


rule shards:
    input:
        expand(f"{E}/shards/{{scenario}}/manifest.json", scenario=PLAN.all_scenarios()),
