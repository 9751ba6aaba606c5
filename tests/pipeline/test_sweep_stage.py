"""Stage adapters: the sweep refuses unstable materials before any solve."""
from __future__ import annotations

import pytest

from liverforce.config import compose
from liverforce.pipeline.sweep import material_checks
from liverforce.sweep.design import SweepError, build_cases


def test_study_mooney_rivlin_constants_are_refused_before_solving():
    cfg = compose(["material=mooney_rivlin_study"])
    stable, bulk = material_checks(cfg["material"]["stability_stretch"])
    ok, why = stable(cfg["material"]["model"], cfg["material"]["params_mpa"])
    assert not ok and "uniaxial" in why and "0.865" in why
    with pytest.raises(SweepError, match="not Drucker-stable"):
        build_cases("I", {"n_cases": 4, "exertion": "fixed", "material": "fixed"}, ["g"], {}, cfg["material"],
                    cfg["sweep"]["force"], "sobol", 0, 2, stable, bulk)


def test_study_yeoh_constants_are_stable_and_bulk_follows_nu():
    cfg = compose([])
    stable, bulk = material_checks(cfg["material"]["stability_stretch"])
    ok, why = stable("yeoh", cfg["material"]["params_mpa"])
    assert ok, why
    mu0 = 2 * cfg["material"]["params_mpa"]["C10"]
    assert bulk("yeoh", cfg["material"]["params_mpa"], 0.49) == pytest.approx(2 * mu0 * 1.49 / (3 * 0.02))
