"""One owner of seeds: liverforce.seeds.derive, Plan.seed, and no seed arithmetic anywhere else."""
from __future__ import annotations

import ast
import itertools
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from liverforce.config import compose
from liverforce.pipeline.plan import VALIDATION, Plan
from liverforce.seeds import derive, gmsh_random_seed, liver_rng, liver_seeds, spawn_rngs

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "liverforce"


def test_distinct_stages_and_keys_give_distinct_seeds():
    stages = ["mesh", "mesh.exertion", "sweep", "sweep.exertion", "sweep.case", "train", "split.test", "split.cv",
              "tune.fold", "tune.ax", "torch.batches", "observation", "observation.camera"]
    keys = [(), (0,), (1,), ("I",), ("II",), ("proc-0000",), ("proc-0001",), (0, "I"), ("I", 0), (0, "II")]
    seeds = {(st, k, base): derive(base, st, *k) for st, k, base in itertools.product(stages, keys, (0, 1, 1000))}
    assert len(set(seeds.values())) == len(seeds)  # no two (seed, stage, keys) share a seed
    assert all(0 <= s < 2**31 for s in seeds.values())
    # neighbouring keys are unrelated streams, not offsets of each other
    a, b = derive(0, "sweep.case", 0), derive(0, "sweep.case", 1)
    assert abs(a - b) > 1000


def test_keys_compare_as_text_and_order_matters():
    assert derive(5, "sweep.case", 3) == derive(5, "sweep.case", "3")
    assert derive(5, "sweep", 0, "I") != derive(5, "sweep", "I", 0)
    assert derive(5, "sweep", np.int64(0), np.str_("I")) == derive(5, "sweep", 0, "I")


def test_pinned_values_catch_a_changed_derivation():
    """Computed once (numpy 2.4): a change here changes every seed of every run; do it on purpose only."""
    assert derive(0, "sweep", 0, "I") == 666586745
    assert derive(0, "mesh", "proc-0000") == 1200782311
    assert derive(12345, "split.test") == 259304703
    # the procedural livers' streams are the ones every liver was drawn with (shapes unchanged)
    assert liver_rng(0, "shape").uniform() == 0.8382446460759589
    assert liver_rng(7, "volume").uniform() == 0.697454877724133


def test_same_in_another_process_whatever_the_hash_seed():
    code = ("from liverforce.seeds import derive; "
            "print(derive(3, 'sweep', 0, 'IV'), derive(3, 'observation', 'II-000007'), derive(0, 'mesh', 'val-1000'))")
    here = f"{derive(3, 'sweep', 0, 'IV')} {derive(3, 'observation', 'II-000007')} {derive(0, 'mesh', 'val-1000')}"
    for hash_seed in ("1", "2"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT,
                             env={**os.environ, "PYTHONHASHSEED": hash_seed}, timeout=120).stdout.strip()
        assert out == here


@pytest.mark.parametrize("bad", [-1, 1.5, "3", True])
def test_refuses_what_is_not_a_non_negative_integer(bad):
    with pytest.raises(ValueError):
        derive(bad, "sweep")
    with pytest.raises(ValueError):
        spawn_rngs(-1, 3)


def test_helpers():
    assert list(liver_seeds(1000, 3)) == [1000, 1001, 1002]
    assert gmsh_random_seed(0) == 1 and gmsh_random_seed(41) == 42  # gmsh's default seed is 1
    assert 1 <= gmsh_random_seed(2**31 - 1) <= 2**31 - 1  # a derived seed stays in gmsh's int range
    a, b = spawn_rngs(derive(0, "observation.camera", "c"), 2)
    assert a.uniform() != b.uniform()


def test_plan_owns_the_runs_seeds():
    plan = Plan(compose(["experiment=smoke"]))
    again = Plan(compose(["experiment=smoke"]))
    scenarios = plan.all_scenarios()
    sweep = [plan.sweep_params(s)["seed"] for s in scenarios]
    assert sweep == [again.sweep_params(s)["seed"] for s in scenarios]  # same config, same seeds
    assert sweep == [derive(plan.cfg["seed"], "sweep", plan.cfg["sweep"]["seed"], s) for s in scenarios]
    assert len(set(sweep)) == len(scenarios) and VALIDATION in scenarios
    meshes = {g: plan.seed("mesh", g) for g in plan.all_geometries}
    assert len(set(meshes.values())) == len(meshes)
    assert plan.train_seed() == derive(plan.cfg["seed"], "train", plan.cfg["train"]["seed"])
    # the group seeds move only their own stage; the master seed moves every stage
    other_sweep = Plan(compose(["experiment=smoke", "sweep.seed=3"]))
    assert other_sweep.sweep_params("I")["seed"] != plan.sweep_params("I")["seed"]
    assert other_sweep.train_seed() == plan.train_seed()
    assert other_sweep.seed("mesh", "proc-0000") == plan.seed("mesh", "proc-0000")
    master = Plan(compose(["experiment=smoke", "seed=1"]))
    assert master.sweep_params("I")["seed"] != plan.sweep_params("I")["seed"]
    assert master.train_seed() != plan.train_seed()
    assert master.seed("mesh", "proc-0000") != plan.seed("mesh", "proc-0000")


def test_negative_config_seeds_are_refused():
    from liverforce.config import ConfigError

    for key in ("seed", "sweep.seed", "train.seed"):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            compose([f"{key}=-1"])


# --------------------------------------------------------------------------
# no seed arithmetic outside liverforce/seeds.py
# --------------------------------------------------------------------------

_ARITHMETIC = (ast.Add, ast.Sub, ast.Mult, ast.FloorDiv, ast.Mod, ast.Pow, ast.LShift, ast.RShift, ast.BitXor)
_MAGIC = {7919, 104729, 1_000_003, 0x11FE5, 0x7015}


def _mentions_seed(node) -> bool:
    for n in ast.walk(node):
        if isinstance(n, ast.Name) and "seed" in n.id.lower():
            return True
        if isinstance(n, ast.Attribute) and "seed" in n.attr.lower():
            return True
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and "seed" in n.value.lower():
            return True
    return False


def _is_text(node) -> bool:
    return isinstance(node, ast.JoinedStr) or (isinstance(node, ast.Constant) and isinstance(node.value, str))


def seed_derivations(path: Path) -> list[str]:
    """Hand-made seed derivations in one file: arithmetic on a seed, SeedSequence / crc32 / list-seeded
    generators, and the old magic offsets."""
    found = []
    for n in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(n, ast.BinOp) and isinstance(n.op, _ARITHMETIC) and not (_is_text(n.left) or _is_text(n.right)) \
                and (_mentions_seed(n.left) or _mentions_seed(n.right)):
            found.append(f"{n.lineno}: {ast.unparse(n)}")
        elif isinstance(n, ast.Call):
            name = ast.unparse(n.func)
            if name.endswith(("SeedSequence", "crc32")) or (
                    name.endswith("default_rng") and n.args and isinstance(n.args[0], (ast.List, ast.Tuple))):
                found.append(f"{n.lineno}: {ast.unparse(n)}")
        elif isinstance(n, ast.Constant) and type(n.value) is int and n.value in _MAGIC:
            found.append(f"{n.lineno}: magic {n.value}")
    return found


def test_the_scan_finds_the_old_derivations():
    """The checker itself: every way seeds were derived before liverforce.seeds is caught."""
    import tempfile

    old = ("import zlib\nimport numpy as np\n"
           "a = params['seed'] * 7919 + i\nb = int(seed) * 1_000_003 + i\nc = s['seed'] * 10 + offset\n"
           "d = np.random.default_rng([int(seed), 31])\n"
           "e = np.random.SeedSequence([int(seed), zlib.crc32(gid.encode())])\nf = seed + k\n"
           "g = f'{seed}' + 'x'\n")
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "old.py"
        p.write_text(old)
        lines = {int(x.split(":")[0]) for x in seed_derivations(p)}
    assert lines == {3, 4, 5, 6, 7, 8}  # not line 9 (text)


def test_no_seed_arithmetic_outside_liverforce_seeds():
    found = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "liverforce/seeds.py":
            continue
        hits = seed_derivations(path)
        if hits:
            found[rel] = hits
    assert not found, f"derive seeds with liverforce.seeds.derive (or Plan.seed), not by hand: {found}"


def test_rules_take_seeds_from_the_plan():
    for smk in sorted((ROOT / "workflow" / "rules").glob("*.smk")):
        text = smk.read_text()
        assert 'config_slice("seed")' not in text, f"{smk.name}: the master seed reaches jobs through PLAN.seed"
        for line in text.splitlines():
            if "seed" in line and not line.strip().startswith("#"):
                assert "PLAN.seed(" in line or "PLAN.train_seed()" in line, f"{smk.name}: {line.strip()}"


def test_every_stage_in_use_is_documented_in_liverforce_seeds():
    import liverforce.seeds as seeds_mod

    used = set()
    files = [*PKG.rglob("*.py"), *(ROOT / "workflow" / "rules").glob("*.smk")]
    for path in files:
        if path.suffix == ".smk":
            used |= set(re.findall(r"PLAN\.seed\(\"([\w.]+)\"", path.read_text()))
            continue
        for n in ast.walk(ast.parse(path.read_text())):
            if isinstance(n, ast.Call) and ast.unparse(n.func).split(".")[-1] in ("derive", "seed"):
                pos = 1 if ast.unparse(n.func).split(".")[-1] == "derive" else 0
                if len(n.args) > pos and isinstance(n.args[pos], ast.Constant) and isinstance(n.args[pos].value, str):
                    used.add(n.args[pos].value)
    assert {"mesh", "sweep", "train", "split.test"} <= used
    undocumented = sorted(s for s in used if f"    {s} " not in seeds_mod.__doc__)
    assert not undocumented, f"list these stages in liverforce/seeds.py's docstring: {undocumented}"
