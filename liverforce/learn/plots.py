"""Evaluation figures (matplotlib, Agg backend): predicted vs true per axis, error histogram."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liverforce.atomic import atomic_path


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def evaluation_figures(force_true: np.ndarray, force_pred: np.ndarray, out_dir: str | Path, title: str = "") -> list[Path]:
    """Write ``pred_vs_true_{x,y,z}.png`` and ``error_histogram.png`` to ``out_dir``; return the paths.

    Forces in N, source frame. The histogram shows ``||F^ - F||`` per case.
    """
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t = np.asarray(force_true, dtype=np.float64)
    p = np.asarray(force_pred, dtype=np.float64)
    paths = []
    for j, ax_name in enumerate("xyz"):
        fig, ax = plt.subplots(figsize=(4, 4), dpi=100)
        lo = float(min(t[:, j].min(), p[:, j].min()))
        hi = float(max(t[:, j].max(), p[:, j].max()))
        ax.plot([lo, hi], [lo, hi], color="0.6", lw=1, label="ideal")
        ax.scatter(t[:, j], p[:, j], s=8, alpha=0.7)
        ax.set_xlabel(f"true F{ax_name} (N)")
        ax.set_ylabel(f"predicted F{ax_name} (N)")
        ax.set_title(f"{title} F{ax_name}".strip())
        ax.set_aspect("equal", adjustable="datalim")
        fig.tight_layout()
        path = out / f"pred_vs_true_{ax_name}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp)
        plt.close(fig)
        paths.append(path)
    err = np.linalg.norm(p - t, axis=1)
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=100)
    ax.hist(err, bins=min(30, max(5, len(err) // 3)))
    ax.set_xlabel("|F_pred - F_true| (N)")
    ax.set_ylabel("cases")
    ax.set_title(f"{title} force error".strip())
    fig.tight_layout()
    path = out / "error_histogram.png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    paths.append(path)
    return paths
