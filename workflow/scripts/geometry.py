"""Snakemake adapter: geometry stage (see liverforce.pipeline.geometry.make_geometry)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.geometry import make_geometry

setup_job(snakemake.log[0], snakemake.threads, outputs=snakemake.output)  # noqa: F821
make_geometry(snakemake.params.spec, snakemake.output.surface, snakemake.output.meta)  # noqa: F821
