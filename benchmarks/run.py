"""Run every benchmark (benchmarks/bench_*.py) one after the other.

    python benchmarks/run.py            # all, full size
    python benchmarks/run.py --quick    # all, small sizes
    python benchmarks/run.py mesh fem   # only bench_mesh.py and bench_fem.py

Benchmarks run one at a time (2 cores: never two at once) with one thread per
pool unless a benchmark measures threading itself.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from liverforce.pipeline.job import thread_env

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    names = [a for a in argv if not a.startswith("-")]
    scripts = sorted(HERE.glob("bench_*.py"))
    if names:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in names]
    env = thread_env(1, {**os.environ, "PYTHONPATH": str(HERE.parent)}, override=False)
    rc = 0
    for s in scripts:
        print(f"\n##### {s.name}", flush=True)
        rc |= subprocess.call([sys.executable, str(s)] + (["--quick"] if quick else []), env=env)
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
