"""Snakemake adapter: sweep stage (see liverforce.pipeline.sweep.make_sweep)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.sweep import make_sweep

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
make_sweep(sm.params.sweep, list(sm.input.meshes), sm.output.cases, sm.output.report)
