"""The one error type of the serving layer.

Every input that would give a silently wrong force is refused with a
:class:`PredictionInputError` whose message names the input, what is wrong
with it and what to do (wrong shape, NaN/inf, too few points, units off the
model's training scale, an exertion point off the surface, a model bundle of
another format version, a shard of another schema version).
"""

from __future__ import annotations


class PredictionInputError(ValueError):
    """An input to a force prediction (data, context or model file) cannot be used as given."""


class OffSurfaceError(PredictionInputError):
    """An exertion point too far from the pre-operative surface (or the mesh's); ``point_mm``: it, in the model's
    frame (RAS mm), so that a caller that knows where the training cases pressed can say so."""

    def __init__(self, message: str, point_mm=None):
        super().__init__(message)
        self.point_mm = point_mm
