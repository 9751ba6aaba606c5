"""Snakemake adapter: simulate one shard (see liverforce.pipeline.simulate.simulate_shard)."""
from liverforce.layout import progress_of_shard
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.simulate import simulate_shard

sm = snakemake  # noqa: F821
# the progress file is the job's own too (not a declared output: it changes while the job runs)
setup_job(sm.log[0], sm.threads, outputs=[*sm.output, progress_of_shard(sm.output.shard)])
simulate_shard(sm.input.cases, list(sm.input.meshes), int(sm.wildcards.shard), sm.params.simulate,
               sm.params.boundary, sm.params.dataset, sm.output.shard, material=sm.params.material)
