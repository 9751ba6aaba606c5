"""Every `snakemake` command in the code blocks of README.md and of its guides runs as written, as a dry run.

Each command line of a fenced code block (continuation lines joined, ``#``
comments dropped, ``a && b`` split) whose program is ``snakemake`` is run
with ``-n --snakefile <repo>/Snakefile --directory <tmp>`` put right after the
program, from the repository folder (so relative paths such as
``workflow/profiles/slurm`` resolve as for a user), exactly as the README
writes the rest of it (the SLURM profile lines included: a dry run through the
executor plugin needs no cluster, see tests/faults/test_cluster.py).  So a
target after ``--config`` (read by Snakemake as a config entry), an unknown
option, a bad override or a key the config does not know fails here.

Paths under ``/data/`` in the README are placeholders for the user's files.
An imported liver's files are inputs of the geometry and mesh rules, so
Snakemake needs them to exist even in a dry run (a missing one stops it before
any job, naming the file): each ``/data/...`` path is moved under the run's
own folder, where an empty placeholder file is made (a dry run does not read
it); nothing else is substituted. The test also checks that each has a
suffix the importer reads.
"""

from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import pytest

from test_workflow import ROOT, SNAKEMAKE

README = ROOT / "README.md"
# the README's sections in full; not the experiment record, which quotes commands as they were run then
GUIDES = sorted(p for p in (ROOT / "docs").glob("*.md") if p.name != "experiments.md")
TEXT = "\n".join(p.read_text() for p in [README, *GUIDES])


def readme_snakemake_commands(text: str) -> list[list[str]]:
    """Argument lists (after the program) of every ``snakemake`` command in the fenced code blocks."""
    commands = []
    for block in re.findall(r"^```[a-z]*\n(.*?)^```", text, flags=re.M | re.S):
        joined = re.sub(r"\\\n\s*", " ", block)  # continuation lines
        for line in joined.splitlines():
            words = shlex.split(line, comments=True)
            while words:
                cut = words.index("&&") if "&&" in words else len(words)
                part, words = words[:cut], words[cut + 1:]
                if part and Path(part[0]).name == "snakemake":
                    commands.append(part[1:])
    return commands


COMMANDS = readme_snakemake_commands(TEXT)


def test_the_readme_has_snakemake_commands():
    assert len(COMMANDS) >= 10, COMMANDS
    assert any("--profile" in c for c in COMMANDS) and any("--config" in c for c in COMMANDS)


def test_the_extraction_joins_continuations_and_splits_chains():
    text = "```bash\n.venv/bin/snakemake --unlock && .venv/bin/snakemake --cores 2  # resume\n" \
           ".venv/bin/snakemake --profile p --config a=1 \\\n    --default-resources x=1\n" \
           ".venv/bin/mlflow ui\n```\nnot code: snakemake --cores 1\n"
    assert readme_snakemake_commands(text) == [
        ["--unlock"], ["--cores", "2"], ["--profile", "p", "--config", "a=1", "--default-resources", "x=1"]]


def test_targets_never_follow_config():
    """`--config a=1 target` makes `target` a config entry; the dry runs catch it, this names it."""
    for args in COMMANDS:
        if "--config" in args:
            after = args[args.index("--config") + 1:]
            values = after[:next((i for i, a in enumerate(after) if a.startswith("-")), len(after))]
            assert all("=" in v for v in values), f"target after --config in: snakemake {shlex.join(args)}"


def test_placeholder_files_have_supported_suffixes():
    from liverforce.geometry.importers import SUPPORTED_SUFFIXES

    paths = re.findall(r"path:(/data/[^,}\]\s]+)", TEXT)
    assert paths
    for p in paths:
        assert p.lower().endswith(SUPPORTED_SUFFIXES), p


def dry_run(args: list[str], directory: Path) -> tuple[int, str]:
    """``snakemake -n`` of the README's ``args`` in ``directory``, its ``/data/...`` placeholder files made there."""
    data = directory / "data"
    for p in {m for a in args for m in re.findall(r"/data/[^,}\]\s]+", a)}:
        (data / p[len("/data/"):]).parent.mkdir(parents=True, exist_ok=True)
        (data / p[len("/data/"):]).touch()
    args = [a.replace("/data/", f"{data}/") for a in args]
    cmd = [SNAKEMAKE, "-n", "--snakefile", str(ROOT / "Snakefile"), "--directory", str(directory), *args]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def dry_runs(tmp_path_factory) -> dict[tuple[str, ...], tuple[int, str]]:
    """All README commands dry-run two at a time (each ~5-10 s, mostly building the DAG), each in its own folder."""
    from concurrent.futures import ThreadPoolExecutor

    unique = list(dict.fromkeys(tuple(c) for c in COMMANDS))
    # The folders are made here, before the threads: pytest's tmp_path_factory is not thread-safe. On an xdist worker
    # its first call empties and remakes the worker's base folder, so two threads making it at once could delete it
    # under the other (CI at 9a81de3: all 16 dry runs failed with FileNotFoundError for popen-gw0).
    folders = [tmp_path_factory.mktemp("readme") for _ in unique]
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = pool.map(lambda c, d: dry_run(list(c), d), unique, folders)
        return dict(zip(unique, results))


@pytest.mark.slow  # 16 dry runs: in the CI slow set, keeping the default set well under 15 minutes
@pytest.mark.parametrize("args", COMMANDS, ids=[shlex.join(c)[:80] for c in COMMANDS])
def test_readme_command_dry_runs(args, dry_runs):
    rc, out = dry_runs[tuple(args)]
    assert rc == 0, f"README command failed as a dry run: snakemake {shlex.join(args)}\n{out[-3000:]}"
    if "--unlock" not in args:
        assert "This was a dry-run" in out or "Nothing to be done" in out, out[-2000:]


def test_a_target_after_config_does_fail(tmp_path):
    """The mistake this file guards against really fails a dry run (the README once had it)."""
    rc, out = dry_run(["--cores", "2", "--config", "experiment=smoke", "shards"], tmp_path)
    assert rc != 0 and "Unparsable value: 'shards'" in out


def test_the_guides_are_read():
    """The README's sections moved to docs/ keep their commands under test: the lab's liver guide has some."""
    assert {p.name for p in GUIDES} >= {"own-liver.md", "use-a-model.md", "simulation.md"}
    assert readme_snakemake_commands((ROOT / "docs" / "own-liver.md").read_text())
    assert all(c in COMMANDS for c in readme_snakemake_commands((ROOT / "docs" / "own-liver.md").read_text()))
