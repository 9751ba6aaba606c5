"""A neo-Hookean material from a paper's Young's modulus and Poisson ratio (Pa or MPa), converted to MPa.

The check that can fail: the material built from the converted constants must
give back the stated E and nu through the small-strain identities
``E = 9 K mu / (3 K + mu)`` and ``nu = (3 K - 2 mu) / (2 (3 K + mu))``, with
``mu`` the built material's initial shear modulus and ``K`` its bulk modulus.
"""

from __future__ import annotations

import logging

import pytest

from liverforce.config import ConfigError, compose
from liverforce.fem.materials import make_material, neo_hookean_from_young


def _E_nu(mat):
    mu, K = mat.mu0, mat.bulk
    return 9 * K * mu / (3 * K + mu), (3 * K - 2 * mu) / (2 * (3 * K + mu))


@pytest.mark.parametrize("E, unit, nu", [(4500.0, "Pa", 0.49), (0.0045, "MPa", 0.49), (14.9, "kPa", 0.45),
                                         (2.0e5, "Pa", 0.3)])
def test_converted_constants_give_back_e_and_nu(E, unit, nu):
    params, note = neo_hookean_from_young(E, nu, unit=unit)
    mat = make_material("neo_hookean", params, nu=nu)
    E_mpa = E * {"Pa": 1e-6, "kPa": 1e-3, "MPa": 1.0}[unit]
    E_back, nu_back = _E_nu(mat)
    assert E_back == pytest.approx(E_mpa, rel=1e-9)
    assert nu_back == pytest.approx(nu, rel=1e-9)
    assert params["C10"] == pytest.approx(E_mpa / (4 * (1 + nu)), rel=1e-12)  # C10 = mu / 2
    assert f"nu {nu:g}" in note and "C10" in note and "MPa" in note


def test_the_logged_conversion_states_units_and_values(caplog):
    with caplog.at_level(logging.INFO, logger="liverforce"):
        cfg = compose(["material=neo_hookean_from_e", "material.E_pa=4500", "material.nu=0.49"])
    assert cfg["material"]["params_mpa"] == {"C10": pytest.approx(0.000755033557, rel=1e-9)}
    line = "E 4.5 kPa, nu 0.49 -> mu 0.00151 MPa, C10 0.000755 MPa, K 0.075 MPa (D1 = 2/K = 26.67 1/MPa)"
    assert line in caplog.text and line in cfg["material"]["conversion"]


def test_e_in_pa_is_the_same_material_as_the_neo_hookean_group():
    """config/material/neo_hookean_from_e.yaml (E 14.9 kPa, nu 0.49) is config/material/neo_hookean.yaml."""
    a = compose(["material=neo_hookean_from_e"])["material"]
    b = compose(["material=neo_hookean"])["material"]
    assert a["params_mpa"]["C10"] == pytest.approx(b["params_mpa"]["C10"], rel=1e-12)
    via_mpa = compose(["material=neo_hookean_from_e", "material.E_pa=null", "material.E_mpa=0.0149"])["material"]
    assert via_mpa["params_mpa"] == a["params_mpa"] and via_mpa["E_mpa"] == 0.0149 and "E_pa" not in via_mpa


def test_a_config_without_e_keeps_its_material_slice_unchanged():
    m = compose([])["material"]
    assert "E_pa" not in m and "E_mpa" not in m and "conversion" not in m


def test_the_converted_material_passes_the_sweeps_drucker_check():
    from liverforce.pipeline.sweep import material_checks

    m = compose(["material=neo_hookean_from_e", "material.E_pa=4500"])["material"]
    stable, _ = material_checks(m["stability_stretch"], m["nu"])
    ok, message = stable(m["model"], m["params_mpa"])
    assert ok, message


@pytest.mark.parametrize("overrides, key, text", [
    (["material=neo_hookean_from_e", "material.model=yeoh"], "material.E_pa", "defines a neo_hookean material"),
    (["material=neo_hookean_from_e", "material.E_pa=1e4", "material.E_mpa=0.01"], "material.E_pa",
     "given twice.*both on the command line"),  # the preset's E_pa alone gives way: tests/test_lab_config.py
    (["material=neo_hookean_from_e", "material.E_pa=-3"], "material.E_pa", "must be > 0"),
    (["material=neo_hookean_from_e", "+material.params_mpa.C10=0.01"], "material.params_mpa",
     "not both"),
    (["material=neo_hookean_from_e", "material.nu=0.5"], "material.nu", "Poisson ratio must be in"),
])
def test_bad_young_settings_are_refused_by_key(overrides, key, text):
    with pytest.raises(ConfigError, match=rf"'{key}'.*{text}"):
        compose(overrides)
