# Stages 4-5: FE simulation of one shard of cases -> one Parquet shard; the manifest.
import math


rule simulate:
    input:
        cases=P.cases(),
        meshes=lambda wc: [P.mesh(g) for g in PLAN.scenario_geometries(wc.scenario)],
    output:
        shard=P.shard(),
    params:
        simulate=config_slice("simulate"),
        boundary=config_slice("boundary"),
        dataset=config_slice("dataset"),
        material=config_slice("material"),  # the stiffness probe's reference material
    log:
        P.log("simulate", "{scenario}-{shard}"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        # SLURM --time, --mem, more on each retry: every case at 15 s (on the default livers 99.9 % of the cases
        # take under 8 s, the slowest converged one 28-39 s) plus one case at the whole wall-time safety net
        # (simulate.time_limit_s; the budget that decides is simulate.max_total_iter, counted in iterations)
        mem_mb=lambda wc, attempt: 4000 * attempt,
        runtime=lambda wc, attempt: attempt * (5 + math.ceil(
            (config_slice("sweep", "cases_per_shard") * 15 + config_slice("simulate", "time_limit_s")) / 60)),
    script:
        "../scripts/simulate.py"


rule manifest:
    input:
        shards=lambda wc: [P.shard(wc.scenario, s) for s in PLAN.shard_ids(wc.scenario)],
    output:
        manifest=P.manifest(),
    log:
        P.log("manifest", "{scenario}"),
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
        [P.manifest(s) for s in PLAN.all_scenarios()],
