"""Snakemake adapter: the run report (see liverforce.report)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.report import make_report

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
make_report(list(sm.input.models), list(sm.input.manifests), sm.input.validation, list(sm.input.features),
            list(sm.input.pictures), sm.params.experiment, sm.output.html, studies=list(sm.input.studies),
            setup=dict(sm.params.setup), surfaces=list(sm.input.surfaces),
            physics=(list(sm.input.physics) or [None])[0])
