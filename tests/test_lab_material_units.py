"""A lab's material constants in the wrong unit are refused when the config is composed, naming the key, the
value and the likely mix-up: Pa or kPa given as MPa made a liver a million or a thousand times too stiff, kPa
given as Pa one a thousand times too soft, and both passed every check (they are Drucker-stable)."""

from __future__ import annotations

import pytest

from liverforce.config import ConfigError, compose


@pytest.mark.parametrize("overrides, key, says", [
    (["material=neo_hookean_from_e", "material.E_pa=null", "material.E_mpa=14900"], "material.E_mpa",
     r"mu0 = 5e\+03 MPa .*if 14900 is in Pa, give E_pa=14900 \(E_mpa=0.0149\)"),
    # kPa given as MPa: the fix is E_pa=14900 (not "E_pa=14.9", 14.9 Pa, a thousand times too soft in turn)
    (["material=neo_hookean_from_e", "material.E_pa=null", "material.E_mpa=14.9"], "material.E_mpa",
     r"mu0 = 5 MPa .*if 14.9 is in kPa, give E_pa=14900 \(E_mpa=0.0149\)$"),
    (["material=neo_hookean_from_e", "material.E_pa=14.9"], "material.E_pa",
     r"mu0 = 5e-06 MPa \(5 Pa\).*if 14.9 is in kPa, give E_pa=14900"),
    (["material=neo_hookean", "material.params_mpa.C10=2500"], "material.params_mpa",
     r"\{'C10': 2500.0\} gives .*mu0 = 5e\+03 MPa.*in Pa, divide them by 1e6 \(mu0 0.005 MPa\)"),
    (["material=yeoh", "material.params_mpa.C10=1.61", "material.params_mpa.C20=12.5", "material.params_mpa.C30=5.31"],
     "material.params_mpa", r"mu0 = 3.22 MPa.*in kPa by 1e3 \(mu0 0.00322 MPa\)"),
])
def test_constants_in_the_wrong_unit_are_refused_with_the_likely_fix(overrides, key, says):
    with pytest.raises(ConfigError, match=f"config key '{key}': .*outside the 1e-05-1 MPa") as err:
        compose(["experiment=smoke", *overrides])
    assert err.match(says)


@pytest.mark.parametrize("overrides", [
    ["material=neo_hookean_from_e", "material.E_pa=14900"],        # the README's liver
    ["material=neo_hookean_from_e", "material.E_pa=600"],          # a soft ex-vivo liver
    ["material=neo_hookean_from_e", "material.E_pa=2.5e6"],        # a stiff silicone phantom
    ["material=yeoh"], ["material=neo_hookean"],
    ["material=mooney_rivlin_study"],                              # judged by the stability check, not here
])
def test_liver_and_phantom_constants_pass(overrides):
    compose(["experiment=smoke", *overrides])


@pytest.mark.parametrize("nu", [0.49999, 0.4999999])
def test_a_poisson_ratio_a_hair_below_one_half_is_refused_naming_it(nu):
    """nu = 0.4999999 passed (it is below 0.5) and every case then spent its Newton budget, 40 s each, failing."""
    with pytest.raises(ConfigError, match=rf"config key 'material.nu': Poisson ratio {nu} makes the bulk modulus "
                                          r".* times the shear modulus.*give at most 0.4999"):
        compose(["experiment=smoke", "material=neo_hookean_from_e", f"material.nu={nu}"])


@pytest.mark.parametrize("nu", [0.45, 0.49, 0.499, 0.4999])
def test_nearly_incompressible_ratios_that_converge_pass(nu):
    m = compose(["experiment=smoke", "material=neo_hookean_from_e", f"material.nu={nu}"])["material"]
    assert m["nu"] == nu and f"nu {nu:g}" in m["conversion"]


@pytest.mark.parametrize("overrides, key", [
    (["material=neo_hookean_from_e", "material.E_pa=null", "material.E_mpa=1e-5"], "material.E_mpa"),
    (["material=neo_hookean", "material.params_mpa.C10=2.5e-6"], "material.params_mpa"),
])
def test_constants_too_soft_are_refused_without_a_hint_that_would_soften_them_further(overrides, key):
    """A modulus below any liver's in MPa: no unit mix-up divides it up to a liver's, so no 'give it in Pa' or
    'divide by 1e3' (which made it softer still)."""
    with pytest.raises(ConfigError, match=f"config key '{key}': .*outside the 1e-05-1 MPa") as err:
        compose(["experiment=smoke", *overrides])
    assert "divide" not in str(err.value) and "E_pa=" not in str(err.value)
