"""Identifiability reports and plots of learning runs.

Spread of per-spring fits, curvature of the loss (undetermined directions), learning curves
and scans.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..outputs import save_figure
from ..sim.springs import difference
from .parameters import Parameters
from .series import Series
from .trainer import Record

__all__ = [
    "active_springs",
    "relative_error",
    "spread_report",
    "curvature_report",
    "plot_history",
    "plot_scan",
    "plot_spread",
    "history_dicts",
]


# ------------------------------------------------------------------- reports and plots
def active_springs(series: Series) -> torch.Tensor:
    """Bool ``(S, D, H, W)``: springs that exist and have at least one end free to move.

    A spring between two fixed (or dragged) nodes never changes length, so no data can
    determine its parameters; identifiability reports leave those out and count them.
    """
    c = torch.as_tensor(series.constrained()).to(torch.float64)[None, None]
    far = c + difference(c, series.grid)[:, :, 0]
    both = (c > 0) & (far > 0)
    return series.spring_mask_tensor() & ~both[0]


def relative_error(value, truth) -> float:
    """``|value - truth| / |truth|`` for numbers."""
    return abs(float(value) - float(truth)) / abs(float(truth))


def spread_report(learned, truth) -> dict:
    """How far per-spring (or per-node) values spread around their true values.

    Args:
        learned: ``(n,)`` learned values.
        truth: ``(n,)`` true values of the same springs (or nodes), in the same order.

    Returns:
        dict: ``n``; quantiles of the ratio learned/true (``min, p05, p25, median, p75, p95,
        max``); ``log_ratio_std``; ``median_rel_error``, ``max_rel_error``;
        ``within_1pct``, ``within_10pct`` (fractions); ``verdict``: "recovered" when 95 %
        are within 10 %, else "not determined by the data".
    """
    a = np.asarray(torch.as_tensor(learned).detach().cpu(), dtype=np.float64).reshape(-1)
    b = np.asarray(torch.as_tensor(truth).detach().cpu(), dtype=np.float64).reshape(-1)
    r = a / b
    rel = np.abs(r - 1)
    q = np.quantile(r, [0, 0.05, 0.25, 0.5, 0.75, 0.95, 1])
    within10 = float(np.mean(rel <= 0.1))
    return {
        "n": int(a.size),
        "ratio": dict(zip(["min", "p05", "p25", "median", "p75", "p95", "max"], map(float, q))),
        "log_ratio_std": float(np.std(np.log(r))),
        "median_rel_error": float(np.median(rel)),
        "max_rel_error": float(rel.max()),
        "within_1pct": float(np.mean(rel <= 0.01)),
        "within_10pct": within10,
        "verdict": "recovered" if within10 >= 0.95 else "not determined by the data",
    }


def curvature_report(params: Parameters, loss, *, rel_threshold: float = 1e-6, max_params: int = 600) -> dict:
    """Eigenvalues of the loss Hessian in the transformed (log) parameters at the current values.

    Directions with curvature below ``rel_threshold * max`` are (practically) not determined
    by the data. Costs one Hessian-vector product per parameter (``max_params`` at most).

    Returns:
        dict: ``n``, ``eigenvalues`` (sorted, descending), ``condition`` (max/min of the
        positive ones), ``undetermined`` (count below the threshold).
    """
    learnable = [p for p in params.parameters() if p.requires_grad]
    n = sum(p.numel() for p in learnable)
    if n > max_params:
        return {"n": n, "skipped": f"more than {max_params} parameters"}
    val = loss(params)
    grads = torch.autograd.grad(val, learnable, create_graph=True)
    g = torch.cat([x.reshape(-1) for x in grads])
    rows = []
    for i in range(n):
        h = torch.autograd.grad(g[i], learnable, retain_graph=True, allow_unused=True)
        rows.append(
            torch.cat(
                [(x if x is not None else torch.zeros_like(p)).reshape(-1) for x, p in zip(h, learnable)]
            ).detach()
        )
    H = torch.stack(rows)
    H = 0.5 * (H + H.T)
    ev = torch.linalg.eigvalsh(H).flip(0).cpu().numpy()
    top = max(float(ev[0]), 1e-300)
    pos = ev[ev > 0]
    return {
        "n": n,
        "eigenvalues": ev.tolist(),
        "condition": float(pos[0] / pos[-1]) if pos.size else math.inf,
        "undetermined": int((ev < rel_threshold * top).sum()),
        "threshold": rel_threshold,
    }


def plot_history(history, path, *, title: str = "learning curve", extra: dict | None = None) -> Path:
    """Loss against iteration (log scale) to ``path`` (PNG).

    ``extra``: more curves ``{label: (iterations, values)}``. Returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(6, 4))
    it = [r.iteration if isinstance(r, Record) else r["iteration"] for r in history]
    ls = [r.loss if isinstance(r, Record) else r["loss"] for r in history]
    ax.semilogy(it, ls, label="loss")
    for label, (x, y) in (extra or {}).items():
        ax.semilogy(x, y, label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (relative mean squared error)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def plot_scan(
    values, losses, marker_at, path, xlabel: str, *, marker: str = "true value", title: str = "scan", logx: bool = False
) -> Path:
    """Loss against one scanned parameter (log loss axis), a vertical line at ``marker_at``.

    Written to ``path`` (PNG). Returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    (ax.loglog if logx else ax.semilogy)(values, losses, ".-")
    ax.axvline(marker_at, color="k", lw=1, label=marker)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(path)


def plot_spread(learned, truth, path, *, title: str = "per-spring recovery") -> Path:
    """Histogram of learned/true ratios (log scale) to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.asarray(torch.as_tensor(learned).detach().cpu(), dtype=np.float64) / np.asarray(
        torch.as_tensor(truth).detach().cpu(), dtype=np.float64
    )
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(np.log10(r), bins=30)
    ax.axvline(0.0, color="k", lw=1)
    ax.set_xlabel("log10(learned / true)")
    ax.set_ylabel("springs")
    ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def history_dicts(history) -> list:
    """The history as JSON-able dicts."""
    return [{"iteration": r.iteration, "loss": r.loss, "grad_norm": r.grad_norm, "seconds": r.seconds} for r in history]
