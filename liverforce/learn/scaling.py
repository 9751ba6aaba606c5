"""Standardisation fitted on the training split only.

``z = (x - mean) / scale``. ``scale`` is the per-column standard deviation,
or, with ``groups``, one pooled standard deviation per group of columns (the
ROI grid: one scale per displacement channel keeps the relative amplitude of
the cells, so near-constant cells far from the tool are not blown up to unit
variance). Zero or non-finite scales become 1 (a constant column stays 0).

Example
-------
>>> import numpy as np
>>> s = Standardizer.fit(np.array([[0.0, 1.0], [2.0, 1.0]]))
>>> s.transform(np.array([[1.0, 1.0]]))
array([[0., 0.]])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Standardizer:
    """Column-wise affine scaling ``z = (x - mean) / scale`` (float64)."""

    mean: np.ndarray
    scale: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, groups: np.ndarray | None = None) -> "Standardizer":
        """Fit on training rows ``x`` ``(n, d)``; ``groups`` ``(d,)`` pools the scale per group."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or len(x) == 0:
            raise ValueError(f"Standardizer.fit needs a non-empty (n, d) array, got shape {x.shape}")
        mean = x.mean(axis=0)
        if groups is None:
            scale = x.std(axis=0)
        else:
            groups = np.asarray(groups)
            scale = np.empty(x.shape[1])
            for g in np.unique(groups):
                cols = groups == g
                scale[cols] = np.sqrt(np.mean((x[:, cols] - mean[cols]) ** 2))
        # a column is constant when its spread is negligible against ITS OWN magnitude (a global
        # threshold let inertia columns ~1e9 mm^5 swallow material constants ~1e-3 MPa)
        scale = np.where(np.isfinite(scale) & (scale > 1e-12 * np.maximum(1.0, np.abs(mean))), scale, 1.0)
        return cls(mean=mean, scale=scale)

    def transform(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.mean) / self.scale

    def inverse_transform(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z, dtype=np.float64) * self.scale + self.mean

    def to_dict(self) -> dict:
        """JSON-ready (Python floats round-trip exactly through ``json``)."""
        return {"mean": self.mean.tolist(), "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Standardizer":
        return cls(mean=np.asarray(d["mean"], dtype=np.float64), scale=np.asarray(d["scale"], dtype=np.float64))
