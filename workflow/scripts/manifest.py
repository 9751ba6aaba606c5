"""Snakemake adapter: write the shard manifest of a scenario."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.simulate import make_manifest

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
make_manifest(list(sm.input.shards), sm.output.manifest)
