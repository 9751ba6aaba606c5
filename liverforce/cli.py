"""The ``liverforce`` command (thin: composes config, hands work to Snakemake or the package).

Examples
--------
liverforce run                                  # = snakemake --cores 2 (default experiment)
liverforce run -e smoke sweep.seed=3            # an experiment + Hydra overrides
liverforce run -e smoke --target shards         # one stage (a rule name or a file)
liverforce config -e smoke                      # print the composed, validated config
liverforce stability yeoh C10=0.00161 C20=0.0125 C30=0.00531
liverforce progress -e smoke                    # sweep progress while Snakemake runs
liverforce show-case II-000012 -e smoke         # picture of one case
liverforce ui                                   # MLflow UI on 127.0.0.1
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

from liverforce.config import PROJECT_ROOT, ConfigError, check_run, compose, tracking_uri


def _overrides(args) -> list[str]:
    out = []
    if getattr(args, "experiment", None):
        out.append(f"experiment={args.experiment}")
    out.extend(args.overrides or [])
    return out


def snakemake_command(cores: int, experiment: str | None, overrides: list[str], targets: list[str],
                      extra: list[str] | None = None) -> list[str]:
    """The snakemake command line equivalent to ``liverforce run``."""
    exe = Path(sys.executable).with_name("snakemake")
    cmd = [str(exe) if exe.exists() else "snakemake", "--cores", str(cores), "--snakefile", str(PROJECT_ROOT / "Snakefile")]
    cfg = []
    if experiment:
        cfg.append(f"experiment={experiment}")
    if overrides:
        cfg.append("overrides=" + " ".join(shlex.quote(o) for o in overrides))
    if cfg:
        cmd += ["--config", *cfg]
    cmd += list(extra or []) + list(targets)
    return cmd


def cmd_run(args) -> int:
    # validate first, with the run-level checks: a bad key or a run that cannot finish (scenario IV on one
    # liver) fails here, before Snakemake starts any job (the Snakefile's compose refuses it too)
    compose(_overrides(args), run=True)
    cmd = snakemake_command(args.cores, args.experiment, args.overrides, args.target or [],
                            (["-n"] if args.dry_run else []) + (["--rerun-incomplete"] if args.rerun_incomplete else []))
    print("+", " ".join(shlex.quote(c) for c in cmd), file=sys.stderr)
    return subprocess.call(cmd, cwd=os.getcwd())


def cmd_config(args) -> int:
    # printing runs nothing: the config is shown even when a run of it would be refused (noted on stderr)
    cfg = compose(_overrides(args), run=False)
    try:
        check_run(cfg)
    except ConfigError as exc:
        print(f"liverforce: note: `liverforce run` (and snakemake) would refuse this config before any job: {exc}",
              file=sys.stderr)
    if args.json:
        print(json.dumps(cfg, indent=2))
    else:
        import yaml

        print(yaml.safe_dump(cfg, sort_keys=False))
    return 0


def cmd_stability(args) -> int:
    from liverforce.fem.materials import make_material
    from liverforce.fem.stability import check_stability

    params = {}
    for kv in args.params:
        k, _, v = kv.partition("=")
        params[k] = float(v)
    mat = make_material(args.model, params, nu=args.nu)
    rep = check_stability(mat, stretch_range=(args.lo, args.hi))
    print(rep.message)
    return 0 if rep.stable else 3


def cmd_ui(args) -> int:
    cfg = compose(_overrides(args), run=False)
    uri = tracking_uri(cfg)
    cmd = [str(Path(sys.executable).with_name("mlflow")), "ui", "--backend-store-uri", uri, "--host", args.host,
           "--port", str(args.port)]
    print("+", " ".join(cmd), file=sys.stderr)
    return subprocess.call(cmd)


def cmd_progress(args) -> int:
    from liverforce.pipeline.plan import Plan
    from liverforce.pipeline.progress import format_progress, sweep_progress

    print(format_progress(sweep_progress(Plan(compose(_overrides(args), run=False)))))
    return 0


def cmd_show_case(args) -> int:
    """Draw one case: deformed surface coloured by |u|, ROI outlined, force arrow."""
    from liverforce.dataset import io as dio
    from liverforce.dataset.plot import plot_case
    from liverforce.layout import scenario_of_case
    from liverforce.mesh.io import read_mesh
    from liverforce.pipeline.plan import Plan

    plan = Plan(compose(_overrides(args), run=False))
    scenario = scenario_of_case(args.case_id)
    shard_dir = plan.paths.shard_dir(scenario)
    known = plan.shard_ids(scenario) if scenario in plan.all_scenarios() else []
    shards = [Path(plan.paths.shard(scenario, s)) for s in known if Path(plan.paths.shard(scenario, s)).exists()]
    if not shards:
        print(f"liverforce: no shards in {shard_dir}; run the sweep first (snakemake ... shards)", file=sys.stderr)
        return 2
    for shard in shards:
        table = dio.read_table(shard)
        ids = table.column("case_id").to_pylist()
        if args.case_id in ids:
            row = table.slice(ids.index(args.case_id), 1).to_pylist()[0]
            mesh = read_mesh(plan.paths.mesh(row["geometry_id"]))
            out = Path(args.out or plan.paths.case_picture(args.case_id))
            plot_case(mesh.points, mesh.facets, row, out, scale=args.scale)
            print(out)
            return 0
    print(f"liverforce: case {args.case_id} not found in {shard_dir}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="liverforce", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("-e", "--experiment", help="experiment (config/experiment/<name>.yaml)")
        sp.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. sweep.seed=3")

    r = sub.add_parser("run", help="run the workflow (Snakemake) for an experiment")
    common(r)
    r.add_argument("--cores", type=int, default=2)
    r.add_argument("--target", action="append", help="a rule name (e.g. shards, models) or an output file")
    r.add_argument("-n", "--dry-run", action="store_true")
    r.add_argument("--rerun-incomplete", action="store_true")
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("config", help="print the composed, validated configuration")
    common(c)
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=cmd_config)

    s = sub.add_parser("stability", help="Drucker stability of a material's constants (MPa)")
    s.add_argument("model")
    s.add_argument("params", nargs="+", help="NAME=VALUE in MPa, e.g. C10=0.00161")
    s.add_argument("--nu", type=float, default=0.49)
    s.add_argument("--lo", type=float, default=0.6)
    s.add_argument("--hi", type=float, default=1.4)
    s.set_defaults(func=cmd_stability)

    pr = sub.add_parser("progress", help="sweep progress: cases done / total and the rate")
    common(pr)
    pr.set_defaults(func=cmd_progress)

    sc = sub.add_parser("show-case", help="picture of one simulated case (PNG)")
    sc.add_argument("case_id", help="e.g. II-000012")
    common(sc)
    sc.add_argument("--out", help="PNG path (default results/<exp>/cases/<case>.png)")
    sc.add_argument("--scale", type=float, default=1.0, help="displacement magnification")
    sc.set_defaults(func=cmd_show_case)

    u = sub.add_parser("ui", help="open the MLflow UI on the run's tracking store (127.0.0.1)")
    common(u)
    u.add_argument("--host", default="127.0.0.1")
    u.add_argument("--port", type=int, default=5000)
    u.set_defaults(func=cmd_ui)

    register_predict(sub)
    return p


def fetch_from_mlflow(ref: str, dst_dir: Path, *, tracking_uri: str | None = None) -> Path:
    """Download a logged model (run id, ``runs:/``/``models:/`` URI, registered name) into ``dst_dir``; its bundle
    directory.

    Imports MLflow only when ``liverforce predict -m`` names such a reference.
    """
    from liverforce.tracking.model import fetch_force_model

    return fetch_force_model(ref, tracking_uri=tracking_uri, dst_dir=dst_dir)


def register_predict(subparsers):
    """The ``predict`` subcommand of :mod:`liverforce.serve.cli`, with models fetched from MLflow by reference."""
    from liverforce.serve.cli import register

    return register(subparsers, fetch=fetch_from_mlflow)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:
        print(f"liverforce: configuration error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
