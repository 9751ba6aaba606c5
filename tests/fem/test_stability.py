"""Drucker stability: the study's MR5 constants are unstable beyond ~10 % strain."""
import pytest

from liverforce.fem.materials import make_material
from liverforce.fem.stability import UnstableMaterialError, check_stability, require_stable

# the study's printed constants, read as Pa -> MPa
MR5_STUDY = {"C10": -584.5e-6, "C01": 863.5e-6, "C11": 3228.7e-6, "C20": -6228.9e-6, "C02": 3328.3e-6}
YEOH_STUDY = {"C10": 1.61e-3, "C20": 12.5e-3, "C30": 5.31e-3}


def test_study_mr5_is_unstable_beyond_ten_percent():
    mat = make_material("mooney_rivlin_5", MR5_STUDY, nu=0.49)
    rep = check_stability(mat, (0.5, 2.0))
    assert not rep.stable
    lo, hi = rep.modes["uniaxial"].around_one
    assert lo == pytest.approx(0.865, abs=0.005) and hi == pytest.approx(1.105, abs=0.005)
    lo, hi = rep.modes["equibiaxial"].around_one
    assert lo == pytest.approx(0.951, abs=0.005) and hi == pytest.approx(1.075, abs=0.005)
    # uniaxial compression at lam is the state of equibiaxial tension at lam^-1/2
    assert rep.modes["uniaxial"].around_one[0] == pytest.approx(rep.modes["equibiaxial"].around_one[1] ** -2, rel=1e-4)
    assert "not Drucker-stable" in rep.message and "uniaxial" in rep.message
    with pytest.raises(UnstableMaterialError, match="mooney_rivlin_5"):
        rep.raise_if_unstable()
    # even a narrow range of +-15 % strain is refused
    assert not check_stability(mat, (0.85, 1.15)).stable
    # but it is stable for tiny strains
    assert check_stability(mat, (0.97, 1.03)).stable


def test_study_yeoh_is_stable():
    mat = make_material("yeoh", YEOH_STUDY, nu=0.49)
    rep = require_stable(mat, (0.6, 1.4))
    assert rep.stable and "stable" in rep.message
    for m in rep.modes.values():
        assert m.intervals == [(pytest.approx(0.6), pytest.approx(1.4))]


def test_neo_hookean_stable_everywhere_and_negative_c20_yeoh_fails():
    assert check_stability(make_material("neo_hookean", {"C10": 1.0}, nu=0.45), (0.2, 5.0)).stable
    soft = make_material("yeoh", {"C10": 1.0, "C20": -0.5, "C30": 0.0}, nu=0.45)
    rep = check_stability(soft, (0.5, 2.0))
    assert not rep.stable
    with pytest.raises(UnstableMaterialError):
        require_stable(soft, (0.5, 2.0))


def test_bad_range():
    with pytest.raises(ValueError, match="stretch_range"):
        check_stability(make_material("neo_hookean", {"C10": 1.0}, nu=0.45), (1.1, 2.0))
