"""The geometric state against the training range: what is warned of as extrapolation, and what is rounding."""

from __future__ import annotations

import numpy as np

from liverforce.learn.state import outside_ranges


def _rows(thickness_mm):
    n = len(thickness_mm)
    return {"exertion_point_mm": np.zeros((n, 3)), "tool_thickness_mm": np.asarray(thickness_mm, float)}


def test_a_value_a_rounding_away_from_a_bound_is_inside_and_one_beyond_it_is_warned_of():
    """Training thickness 80..90 mm. 80 mm less 0.05 % (an exertion point given in metres to 0.1 mm moves it by up
    to 0.06 %) is inside, as is 90 mm plus 0.05 %; 1 % beyond either bound is named, with its direction."""
    ranges = {"tool_thickness_mm": (80.0, 90.0)}
    masks, warnings = outside_ranges(_rows([80.0 * (1 - 5e-4), 90.0 * (1 + 5e-4), 85.0, 79.2, 90.9]), ranges)
    assert masks["tool_thickness_mm"].tolist() == [False, False, False, True, True]
    assert warnings[:3] == [[], [], []]
    assert warnings[3] == ["the tissue under the tool is 79.2 mm, thinner than in every training case (80..90 mm): "
                           "the model extrapolates, expect a larger error"]
    assert "90.9 mm, thicker than in every training case" in warnings[4][0]


def test_one_training_value_is_a_range_of_one():
    """Every training case at one thickness (one liver, one exertion point): a hair off it is inside, 1 % off is
    not."""
    ranges = {"tool_thickness_mm": (84.63, 84.63)}
    masks, warnings = outside_ranges(_rows([84.63 - 1e-4, 84.63 * 1.01]), ranges)
    assert masks["tool_thickness_mm"].tolist() == [False, True]
    assert "(84.63 mm)" in warnings[1][0]
