"""Which scenario-IV model the unseen-liver validation uses."""
from __future__ import annotations

import json

import pytest

from liverforce.config import ConfigError, compose
from liverforce.pipeline.validate import choose_variant


def _metrics(tmp_path, cv):
    paths = []
    for name, c in cv.items():
        p = tmp_path / name / "metrics.json"
        p.parent.mkdir()
        p.write_text(json.dumps({"variant": name, "cv_mse": c, "metrics": {"accuracy_pct": 50.0}}))
        paths.append(p)
    return paths


def test_auto_takes_the_lowest_cross_validation_error(tmp_path):
    paths = _metrics(tmp_path, {"pca_sv": 0.238, "pca_nosv": 0.228, "ae_sv": 0.248})
    k, why = choose_variant(paths, "auto")
    assert k == 1 and "cross-validation" in why and "pca_nosv 0.2280" in why


def test_auto_prefers_the_cross_validation_error_in_newtons(tmp_path):
    """The MSE of scaled targets is not comparable between variants; the MAE in N is, and decides when present."""
    paths = _metrics(tmp_path, {"pca_sv": 0.1, "pca_nosv": 0.5})
    for p, mae in zip(paths, (0.40, 0.25)):
        doc = json.loads(p.read_text())
        p.write_text(json.dumps({**doc, "cv_mae_n": mae}))
    k, why = choose_variant(paths, "auto")
    assert k == 1 and "MAE (N)" in why and "pca_nosv 0.2500" in why


def test_a_named_variant_is_taken_and_an_unknown_one_refused(tmp_path):
    paths = _metrics(tmp_path, {"pca_sv": 0.2, "ae_sv": 0.1})
    assert choose_variant(paths, "pca_sv")[0] == 0
    with pytest.raises(ValueError, match="dae_sv"):
        choose_variant(paths, "dae_sv")


def test_main_is_the_first_listed(tmp_path):
    paths = _metrics(tmp_path, {"pca_sv": 0.3, "ae_sv": 0.1})
    assert choose_variant(paths, "main")[0] == 0


def test_without_tuning_the_first_variant_is_used(tmp_path):
    paths = _metrics(tmp_path, {"pca_sv": None, "ae_sv": 0.1})
    k, why = choose_variant(paths, "auto")
    assert k == 0 and "first" in why


def test_config_refuses_a_validation_variant_that_is_not_trained():
    with pytest.raises(ConfigError, match="validate.variant"):
        compose(["experiment=smoke", "validate.variant=nope"])
    assert compose(["experiment=smoke", "validate.variant=ae_sv"])["validate"]["variant"] == "ae_sv"
    assert compose(["experiment=smoke"])["validate"]["variant"] == "main"
    assert compose([])["validate"]["variant"] == "auto"  # default: chosen on training-side validation
