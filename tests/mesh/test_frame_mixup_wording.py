"""The words of a given exertion point facing away whose mirror lands nowhere visible (audit 96, defect 7).

A liver given in the wrong frame (LPS declared RAS) mirrors the whole liver, points and all: mirroring the
point alone cannot show it, so the warning must not deny a frame mix-up; it names the liver's frame as the fix.
"""

from __future__ import annotations

import numpy as np

from liverforce.mesh.regions import RegionParams
from liverforce.mesh.supports import _facing_words


def test_a_point_facing_away_does_not_deny_a_frame_mix_up_of_the_whole_liver():
    msg = _facing_words("exertion point 2", np.array([0.0, -0.9, 0.4]), 110.0, np.array([0.0, 0.87, 0.5]),
                        RegionParams(), "away", None)
    assert "not that frame mix-up" not in msg and "Likely a frame mix-up" not in msg
    assert "Mirrored in x and y on its own" in msg
    assert "reading the point file in the other frame would not help" in msg
    assert "If the liver itself was given in the wrong frame" in msg and "implausible regions" in msg
    assert "fix the geometry's frame (geometry.imported[].frame), not the points'" in msg
