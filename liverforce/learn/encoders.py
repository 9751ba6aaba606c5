"""ROI feature encoders: PCA, autoencoder (AE) and denoising autoencoder (DAE).

All act on *standardised* ROI features ``x`` (``n x d``) and give a code of
``code_size`` numbers per case.

PCA
    ``z = (x - mu) W^T`` with ``W`` the first ``k`` right singular vectors of
    the centred training matrix (NumPy SVD, signs fixed so the largest entry
    of each component is positive -> deterministic).
AE
    encoder ``d -> h1 -> h2 -> k`` and mirrored decoder, each hidden layer
    ``Linear -> BatchNorm1d -> LeakyReLU(0.2)``, trained with Adam on the
    reconstruction MSE ``||dec(enc(x)) - x||^2``.
DAE
    the same network trained on ``||dec(enc(x~)) - x||^2``: ``x~`` is the
    ROI after the observation model (tool occlusion, point noise) and ``x``
    the clean ROI, plus Gaussian input noise of standard deviation
    ``input_noise`` (standardised units) drawn per batch, so the DAE also
    denoises when no occlusion is configured.

Hidden widths (when not given): ``h1 = max(4k, min(256, d // 2))``,
``h2 = max(2k, min(64, h1 // 2))``.

Persistence: PCA -> ``mean``/``components`` arrays (npz); AE/DAE -> a
``state_dict`` (``torch.save`` / ``torch.load(weights_only=True)``) plus the
JSON ``spec`` that rebuilds the network.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from liverforce.learn.names import ENCODERS as ENCODER_KINDS
from liverforce.learn.torchutil import EpochCallback, forward_numpy, train_loop

#: negative slope of the autoencoders' LeakyReLU
LEAKY_SLOPE = 0.2


class PCAEncoder:
    """Principal component projection (fitted with NumPy SVD)."""

    kind = "pca"

    def __init__(self, mean: np.ndarray, components: np.ndarray):
        self.mean = np.asarray(mean, dtype=np.float64)
        self.components = np.asarray(components, dtype=np.float64)

    @property
    def code_size(self) -> int:
        return int(self.components.shape[0])

    @classmethod
    def fit(cls, x: np.ndarray, code_size: int) -> "PCAEncoder":
        """Fit on training rows ``x`` ``(n, d)``; ``code_size`` is clipped to ``min(n, d)``."""
        x = np.asarray(x, dtype=np.float64)
        mean = x.mean(axis=0)
        _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
        k = int(min(code_size, vt.shape[0]))
        comps = vt[:k]
        signs = np.sign(comps[np.arange(k), np.abs(comps).argmax(axis=1)])
        comps = comps * np.where(signs == 0, 1.0, signs)[:, None]
        return cls(mean, comps)

    def encode(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.mean) @ self.components.T

    def decode(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z, dtype=np.float64) @ self.components + self.mean

    def spec(self) -> dict:
        return {"kind": "pca", "code_size": self.code_size, "n_features": int(self.mean.size)}

    def arrays(self) -> dict[str, np.ndarray]:
        return {"mean": self.mean, "components": self.components}


def _block(d_in: int, d_out: int) -> list[nn.Module]:
    return [nn.Linear(d_in, d_out), nn.BatchNorm1d(d_out), nn.LeakyReLU(LEAKY_SLOPE)]


class AutoEncoderNet(nn.Module):
    """``d -> hidden... -> code -> reversed(hidden)... -> d`` with BatchNorm + LeakyReLU blocks."""

    def __init__(self, n_features: int, code_size: int, hidden: list[int]):
        super().__init__()
        enc: list[nn.Module] = []
        dims = [n_features, *hidden]
        for a, b in zip(dims[:-1], dims[1:]):
            enc += _block(a, b)
        enc.append(nn.Linear(dims[-1], code_size))
        dec: list[nn.Module] = []
        rdims = [code_size, *reversed(hidden)]
        for a, b in zip(rdims[:-1], rdims[1:]):
            dec += _block(a, b)
        dec.append(nn.Linear(rdims[-1], n_features))
        self.encoder = nn.Sequential(*enc)
        self.decoder = nn.Sequential(*dec)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))


def default_hidden(n_features: int, code_size: int) -> list[int]:
    h1 = max(4 * code_size, min(256, n_features // 2))
    h2 = max(2 * code_size, min(64, h1 // 2))
    return [int(h1), int(h2)]


class AutoEncoder:
    """A fitted AE or DAE (``kind`` says which)."""

    def __init__(self, kind: str, net: AutoEncoderNet, spec: dict):
        self.kind = kind
        self.net = net
        self._spec = spec

    @property
    def code_size(self) -> int:
        return int(self._spec["code_size"])

    @classmethod
    def fit(
        cls,
        x_in: np.ndarray,
        x_target: np.ndarray,
        code_size: int,
        *,
        kind: str = "ae",
        hidden: list[int] | None = None,
        epochs: int = 100,
        lr: float = 1e-3,
        batch_size: int = 64,
        seed: int = 0,
        input_noise: float = 0.0,
        on_epoch: EpochCallback | None = None,
    ) -> "AutoEncoder":
        """Train on ``x_in -> x_target`` (``x_in is x_target`` for a plain AE)."""
        n_features = int(np.shape(x_in)[1])
        hidden = list(hidden) if hidden else default_hidden(n_features, code_size)
        spec = {
            "kind": kind,
            "n_features": n_features,
            "code_size": int(code_size),
            "hidden": hidden,
            "input_noise": float(input_noise),
        }
        torch.manual_seed(int(seed))
        net = AutoEncoderNet(n_features, int(code_size), hidden)
        corrupt = None
        if input_noise > 0:

            def corrupt(xb: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
                return xb + input_noise * torch.randn(xb.shape, generator=gen)

        train_loop(
            net, x_in, x_target, epochs=epochs, lr=lr, batch_size=batch_size, seed=seed, corrupt=corrupt,
            on_epoch=on_epoch,
        )
        return cls(kind, net, spec)

    def encode(self, x: np.ndarray) -> np.ndarray:
        return forward_numpy(self.net.encoder, x)

    def decode(self, z: np.ndarray) -> np.ndarray:
        return forward_numpy(self.net.decoder, z)

    def spec(self) -> dict:
        return dict(self._spec)

    @classmethod
    def from_state(cls, spec: dict, state_dict: dict) -> "AutoEncoder":
        net = AutoEncoderNet(spec["n_features"], spec["code_size"], list(spec["hidden"]))
        net.load_state_dict(state_dict)
        net.eval()
        return cls(spec["kind"], net, dict(spec))


Encoder = PCAEncoder | AutoEncoder
