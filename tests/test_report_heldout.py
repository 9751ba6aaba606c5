"""The held-out-exertion-points column: never a number from a fold that trained on too few points, and never
an accuracy below the floor printed bare."""

import json
import re

import test_report
from test_report import _report, _rows, _text

stage_outputs = test_report.stage_outputs  # the hand-made stage outputs (fixture)

NOT_MEASURED = {
    "folds": 2, "n_points": 3, "min_train_points": 3, "n_scored": 0, "metrics_mean": None, "metrics_sd": None,
    "not_measured": "3 exertion points (3 on imp-lab01) in 2 folds leave at most 2 points of a tested liver to "
                    "train a fold on, fewer than the 3 needed; give >= 6 exertion points per liver at 2 folds",
    "per_fold": [{"points": ["imp-lab01#0", "imp-lab01#2"], "n_test": 13, "train_points": {"imp-lab01": 1},
                  "skipped": "fold 1 trains on 1 exertion point of imp-lab01 (fewer than 3: ...)"},
                 {"points": ["imp-lab01#1"], "n_test": 5, "train_points": {"imp-lab01": 2},
                  "skipped": "fold 2 trains on 2 exertion points of imp-lab01 (fewer than 3: ...)"}]}
#: what train wrote before the guard: the absurd mean of a fold that trained on one point
UNGUARDED = {"folds": 2, "n_points": 3, "metrics_mean": {"accuracy_pct": -502887592.90267277, "mae_vec": 8.1e6},
             "metrics_sd": {"accuracy_pct": 711207512.3, "mae_vec": 1.1e7},
             "per_fold": [{"points": ["imp-lab01#0", "imp-lab01#2"], "n_test": 13,
                           "metrics": {"accuracy_pct": -1005775218.7456099, "mae_vec": 16226799.2}},
                          {"points": ["imp-lab01#1"], "n_test": 5,
                           "metrics": {"accuracy_pct": 32.94, "mae_vec": 0.94}}]}
PARTLY = {"folds": 3, "n_points": 4, "min_train_points": 3, "n_scored": 2,
          "metrics_mean": {"accuracy_pct": 81.25, "mae_vec": 0.2},
          "metrics_sd": {"accuracy_pct": 1.5, "mae_vec": 0.01},
          "per_fold": [{"points": ["g#0", "g#1"], "n_test": 6, "train_points": {"g": 2},
                        "skipped": "fold 1 trains on 2 exertion points of g (fewer than 3)"},
                       {"points": ["g#2"], "n_test": 3, "metrics": {"accuracy_pct": 80.2, "mae_vec": 0.2}},
                       {"points": ["g#3"], "n_test": 3, "metrics": {"accuracy_pct": 82.3, "mae_vec": 0.2}}]}
#: 5 points in 2 folds: one fold trains on 2 points (not scored), the other on 3: one fold, no spread
ONE_SCORED = {"folds": 2, "n_points": 5, "min_train_points": 3, "n_scored": 1,
              "metrics_mean": {"accuracy_pct": 71.23, "mae_vec": 0.3}, "metrics_sd": None,
              "per_fold": [{"points": ["g#0", "g#1", "g#2"], "n_test": 9, "train_points": {"g": 2},
                            "skipped": "fold 1 trains on 2 exertion points of g (fewer than 3)"},
                           {"points": ["g#3", "g#4"], "n_test": 6, "metrics": {"accuracy_pct": 71.23, "mae_vec": 0.3}}]}
FOLDS_OK = {"folds": 4, "n_points": 8, "min_train_points": 3, "n_scored": 4,
            "metrics_mean": {"accuracy_pct": 84.04, "mae_vec": 0.2},
            "metrics_sd": {"accuracy_pct": 2.26, "mae_vec": 0.01},
            "per_fold": [{"points": [f"g#{2 * i}", f"g#{2 * i + 1}"], "n_test": 6,
                          "metrics": {"accuracy_pct": a, "mae_vec": 0.2}} for i, a in enumerate((82, 84, 83, 87))]}


def _cells(out, records: dict) -> dict:
    """The held-out column's cell (text) per (scenario, variant) after giving ``records`` to those models."""
    for p in out["metrics"]:
        doc = json.loads(p.read_text())
        key = (doc["scenario"], doc["variant"])
        if key in records:
            p.write_text(json.dumps({**doc, "heldout_points": records[key]}))
    html = _report(out)
    table = html[html.index("<table class='models'>"):]
    table = table[:table.index("</table>")]
    return {(r[0], r[1]): _text(r[-1]) for r in _rows(table, "model")}, html


def test_a_fold_trained_on_too_few_points_gives_its_reason_not_a_number(stage_outputs):
    cells, html = _cells(stage_outputs, {("II", "pca_sv"): NOT_MEASURED, ("II", "pca_nosv"): PARTLY,
                                         ("III", "pca_sv"): FOLDS_OK})
    nm = cells[("II", "pca_sv")]
    assert nm.startswith("not measured: 3 exertion points (3 on imp-lab01) in 2 folds leave at most 2 points")
    assert "give &gt;= 6 exertion points per liver" in nm and not re.search(r"\d+\.\d", nm)
    part = cells[("II", "pca_nosv")]
    assert part.startswith("81.2 ± 1.5 (2 of 3 folds of 4 points scored; not scored: fold 1 trains on 2 exertion")
    # enough points in every fold: printed as before the guard
    assert cells[("III", "pca_sv")] == "84.0 ± 2.3 (4 folds of 8 points)"
    assert "extrapolation" not in cells[("III", "pca_sv")] and "fewer than 3 exertion points" in html


def test_an_accuracy_below_the_floor_is_flagged_as_extrapolation(stage_outputs):
    cells, _ = _cells(stage_outputs, {("II", "pca_sv"): UNGUARDED})
    got = cells[("II", "pca_sv")]
    assert got.startswith("⚠ extrapolation: -5.03e+08 ± 7.11e+08 (below 0 %: the errors exceed the forces")
    assert "lowest -1.01e+09 %" in got and "(2 folds of 3 points)" in got
    assert "-502887592.9" not in got  # never the bare number


def test_a_positive_mean_with_one_fold_below_the_floor_is_flagged(stage_outputs):
    bad = {**FOLDS_OK, "metrics_mean": {"accuracy_pct": 12.0}, "metrics_sd": {"accuracy_pct": 60.0},
           "per_fold": FOLDS_OK["per_fold"][:3] + [{"points": ["g#6", "g#7"], "n_test": 6,
                                                    "metrics": {"accuracy_pct": -200.0}}]}
    cells, _ = _cells(stage_outputs, {("II", "pca_sv"): bad})
    got = cells[("II", "pca_sv")]
    assert got.startswith("⚠ extrapolation: 12.0 ± 60.0") and "lowest -200.0 %" in got


def test_one_scored_fold_is_its_mean_without_a_spread(stage_outputs):
    """One scored fold: the mean alone, no ± (its sd is None; an earlier run's record gave 0.0: not printed)."""
    earlier = {**ONE_SCORED, "metrics_sd": {"accuracy_pct": 0.0, "mae_vec": 0.0}}
    cells, _ = _cells(stage_outputs, {("II", "pca_sv"): ONE_SCORED, ("II", "pca_nosv"): earlier})
    for key in (("II", "pca_sv"), ("II", "pca_nosv")):
        got = cells[key]
        assert got.startswith("71.2 (1 of 2 folds of 5 points scored; not scored: fold 1 trains on 2"), got
        assert "±" not in got
