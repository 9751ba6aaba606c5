"""Deterministic torch set-up and a plain mini-batch training loop.

Same seed + same data + same thread count -> the same weights (CPU): the
seed is set before the weights are initialised, batches come from a
``torch.Generator`` seeded from it, and deterministic algorithms are on.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from liverforce.seeds import derive

#: callback ``on_epoch(epoch, train_loss, val_loss_or_None)``
EpochCallback = Callable[[int, float, "float | None"], None]


def configure_torch(threads: int = 1) -> None:
    """One process-wide torch set-up: ``threads`` intra-op threads, deterministic kernels.

    On a shared 2-core machine use 1 thread per job (STACK_NOTES: 2 threads
    under load were 25x slower).
    """
    if torch.get_num_threads() != int(threads):
        torch.set_num_threads(int(threads))
    torch.use_deterministic_algorithms(True)


def as_tensor(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(x, dtype=np.float32))


def batches(n: int, batch_size: int, gen: torch.Generator) -> list[torch.Tensor]:
    """Shuffled index batches; a trailing batch of one sample joins the previous one (batch norm needs >= 2)."""
    perm = torch.randperm(n, generator=gen)
    bs = max(1, int(batch_size))
    out = list(perm.split(bs))
    if len(out) > 1 and len(out[-1]) == 1:
        out[-2] = torch.cat([out[-2], out.pop()])
    return out


def train_loop(
    model: torch.nn.Module,
    x: np.ndarray,
    y: np.ndarray,
    *,
    epochs: int,
    lr: float,
    batch_size: int,
    seed: int,
    weight_decay: float = 0.0,
    x_val: np.ndarray | None = None,
    y_val: np.ndarray | None = None,
    corrupt: Callable[[torch.Tensor, torch.Generator], torch.Tensor] | None = None,
    on_epoch: EpochCallback | None = None,
) -> dict[str, list[float]]:
    """Adam on the mean squared error; returns ``{"train_loss": [...], "val_loss": [...]}``.

    Parameters
    ----------
    model : torch.nn.Module
        Trained in place (left in ``eval`` mode).
    x, y : (n, d_in), (n, d_out) arrays
        Inputs and targets (already scaled).
    corrupt : callable, optional
        ``corrupt(xb, gen) -> xb'`` applied to each input batch in training
        (the denoising autoencoder's extra input noise).
    on_epoch : callable, optional
        Called after every epoch with ``(epoch, train_loss, val_loss)``.

    Notes
    -----
    ``train_loss`` is the sample-weighted mean of the batch losses in train
    mode (dropout and batch norm active); ``val_loss`` is the MSE in eval mode.
    """
    xt, yt = as_tensor(x), as_tensor(y)
    if len(xt) < 2:
        raise ValueError(f"need at least 2 training samples, got {len(xt)}")
    xv = as_tensor(x_val) if x_val is not None else None
    yv = as_tensor(y_val) if y_val is not None else None
    gen = torch.Generator().manual_seed(derive(seed, "torch.batches"))
    # fused: one kernel per step over all parameters instead of a Python loop over tensors (about 1.5x
    # faster per step for these small networks on CPU); deterministic for a given thread count
    opt = torch.optim.Adam(model.parameters(), lr=float(lr), weight_decay=float(weight_decay), fused=True)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, int(epochs)), eta_min=0.01 * float(lr))
    loss_fn = torch.nn.MSELoss()
    hist: dict[str, list[float]] = {"train_loss": [], "val_loss": []}
    for epoch in range(int(epochs)):
        model.train()
        total = 0.0
        for idx in batches(len(xt), batch_size, gen):
            xb = xt[idx]
            if corrupt is not None:
                xb = corrupt(xb, gen)
            opt.zero_grad()
            loss = loss_fn(model(xb), yt[idx])
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        sched.step()
        train_loss = total / len(xt)
        if not math.isfinite(train_loss):
            raise FloatingPointError(f"training diverged at epoch {epoch} (loss {train_loss}); lower the learning rate")
        val_loss = None
        if xv is not None:
            model.eval()
            with torch.no_grad():
                val_loss = float(loss_fn(model(xv), yv))
            hist["val_loss"].append(val_loss)
        hist["train_loss"].append(train_loss)
        if on_epoch is not None:
            on_epoch(epoch, train_loss, val_loss)
    model.eval()
    return hist


def forward_numpy(model: torch.nn.Module, x: np.ndarray) -> np.ndarray:
    """Eval-mode forward pass, float64 NumPy out."""
    model.eval()
    with torch.no_grad():
        return model(as_tensor(x)).double().numpy()
