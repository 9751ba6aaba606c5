"""Stage adapters: the sweep refuses unstable materials before any solve."""
from __future__ import annotations

import pytest

from liverforce.config import compose
from liverforce.pipeline.sweep import material_checks
from liverforce.sweep.design import SweepError, build_cases


def test_study_mooney_rivlin_constants_are_refused_before_solving():
    cfg = compose(["material=mooney_rivlin_study"])
    stable, bulk = material_checks(cfg["material"]["stability_stretch"], cfg["material"]["nu"])
    ok, why = stable(cfg["material"]["model"], cfg["material"]["params_mpa"])
    assert not ok and "uniaxial" in why and "0.865" in why
    with pytest.raises(SweepError, match="not Drucker-stable"):
        build_cases("I", {"n_cases": 4, "exertion": "fixed", "material": "fixed"}, ["g"], {}, cfg["material"],
                    cfg["sweep"]["force"], "sobol", 0, 2, stable, bulk)


def test_study_yeoh_constants_are_stable_and_bulk_follows_nu():
    cfg = compose([])
    stable, bulk = material_checks(cfg["material"]["stability_stretch"], cfg["material"]["nu"])
    ok, why = stable("yeoh", cfg["material"]["params_mpa"])
    assert ok, why
    mu0 = 2 * cfg["material"]["params_mpa"]["C10"]
    assert bulk("yeoh", cfg["material"]["params_mpa"], 0.49) == pytest.approx(2 * mu0 * 1.49 / (3 * 0.02))


@pytest.mark.parametrize("nu", [0.49, 0.3])
def test_the_drucker_check_builds_the_material_with_the_configured_nu(monkeypatch, nu):
    """The check ran on a nu-0.45 material whatever material.nu said (issue 18): it must check the
    material the cases are simulated with (same constants, same bulk modulus)."""
    import liverforce.fem.stability as stability
    from liverforce.fem.materials import make_material

    cfg = compose([f"material.nu={nu}"])["material"]
    seen = []
    real = stability.check_stability

    def spy(material, *a, **kw):
        seen.append(material)
        return real(material, *a, **kw)

    monkeypatch.setattr(stability, "check_stability", spy)
    stable, bulk = material_checks(cfg["stability_stretch"], cfg["nu"])
    ok, why = stable(cfg["model"], cfg["params_mpa"])
    assert ok, why
    simulated = make_material(cfg["model"], cfg["params_mpa"], nu=cfg["nu"])
    assert [m.bulk for m in seen] == [pytest.approx(simulated.bulk, rel=1e-12)]
    assert bulk(cfg["model"], cfg["params_mpa"], cfg["nu"]) == pytest.approx(simulated.bulk, rel=1e-12)


def test_the_default_checked_stretches_cover_the_default_run_and_its_sampled_constants_are_stable_there():
    """The default Drucker range covers the principal stretches the default run's 2,440 cases reach (0.21-1.91,
    from a fresh clone's shards; docs/simulation.md), and every corner of the sampled box of the default constants
    (+- vary_rel), and the unseen livers' (x validate.material_scale), is stable over it: no case warns that its
    stability is unchecked, and no sampled set is refused."""
    import itertools

    cfg = compose([])
    m = cfg["material"]
    lo, hi = m["stability_stretch"]
    assert lo <= 0.21 and hi >= 1.91
    stable, _ = material_checks(m["stability_stretch"], m["nu"])
    r = m["vary_rel"]
    factors = [1 - r, 1 + r, float(cfg["validate"]["material_scale"])]
    for f in itertools.product(factors, repeat=len(m["params_mpa"])):
        ok, why = stable(m["model"], {k: v * s for (k, v), s in zip(m["params_mpa"].items(), f)})
        assert ok, why
