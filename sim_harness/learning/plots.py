"""Figures of training and evaluation: learning curve, predicted vs target, error breakdown."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from sim_harness.learning.model import AXES

_AXIS_NAMES = {"x": "x (forward)", "y": "y (left)", "z": "z (up)"}


def save_learning_curve(history: list[dict[str, Any]], initial_val_loss: float, path: Path) -> Path:
    """Training and validation loss per epoch (log scale), learning rate, best epoch marked."""
    epochs = [row["epoch"] for row in history]
    fig, (ax, ax_lr) = plt.subplots(
        2, 1, figsize=(7, 5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    ax.plot(epochs, [row["train_loss"] for row in history], label="training", color="C0")
    val_epochs = [0, *epochs] if np.isfinite(initial_val_loss) else epochs
    val = [initial_val_loss, *[row["val_loss"] for row in history]]
    ax.plot(val_epochs, val[-len(val_epochs) :], label="validation", color="C1", marker=".")
    if history:
        best = min(history, key=lambda row: row["val_loss"])
        ax.axvline(best["epoch"], color="0.6", ls="--", lw=1)
        ax.set_title(f"best validation loss {best['val_loss']:.4f} (m/s)² at epoch {best['epoch']}")
    ax.set_yscale("log")
    ax.set_ylabel("MSE (m/s)²")
    ax.legend()
    ax.grid(alpha=0.3)
    ax_lr.plot(epochs, [row["lr"] for row in history], color="C2", drawstyle="steps-post")
    ax_lr.set_yscale("log")
    ax_lr.set_ylabel("learning rate")
    ax_lr.set_xlabel("epoch")
    ax_lr.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def save_pred_vs_target(
    pred: NDArray[np.float32],
    target: NDArray[np.float32],
    metrics: dict[str, Any],
    path: Path,
    title: str = "",
) -> Path:
    """One panel per body axis: predicted against target velocity, identity line, R² and RMSE."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.4))
    lim = float(max(np.abs(target).max(initial=0.5), np.abs(pred).max(initial=0.5))) * 1.05
    for k, (ax, axis) in enumerate(zip(axes, AXES, strict=True)):
        if len(pred) > 4000:
            ax.hist2d(
                target[:, k],
                pred[:, k],
                bins=120,
                range=[[-lim, lim], [-lim, lim]],
                cmin=1,
                norm=matplotlib.colors.LogNorm(),
                cmap="viridis",
            )
        else:
            ax.scatter(target[:, k], pred[:, k], s=4, alpha=0.4, lw=0)
        ax.plot([-lim, lim], [-lim, lim], color="0.3", lw=1)
        m = metrics["per_axis"][axis]
        r2 = "n/a" if m["r2"] is None else f"{m['r2']:.3f}"
        ax.set_title(f"{_AXIS_NAMES[axis]}: R² {r2}, RMSE {m['rmse']:.3f} m/s")
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.set_xlabel("target (m/s)")
        ax.set_ylabel("predicted (m/s)")
        ax.grid(alpha=0.3)
    fig.suptitle(title or f"predicted vs target body-frame velocity, n = {len(pred)}")
    fig.tight_layout()
    return _save(fig, path)


def save_error_breakdown(report: dict[str, Any], path: Path, title: str = "") -> Path:
    """RMSE (bars) and sample count against the number of neighbours and the nearest distance."""
    tables = [
        (key, label)
        for key, label in (
            ("by_n_neighbours", "neighbours within r_max"),
            ("by_nearest_m", "distance to the nearest neighbour (m)"),
        )
        if report.get(key)
    ]
    fig, axes = plt.subplots(1, max(len(tables), 1), figsize=(6.5 * max(len(tables), 1), 4))
    for ax, (key, label) in zip(np.atleast_1d(axes), tables, strict=False):
        rows = report[key]
        x = np.arange(len(rows))
        ax.bar(x, [row["rmse_mps"] for row in rows], color="C0", label="RMSE per axis")
        ax.plot(x, [row["mean_error_mps"] for row in rows], "o-", color="C3", label="mean |error|")
        ax.set_xticks(x, [row["label"] for row in rows], rotation=30)
        ax.set_xlabel(label)
        ax.set_ylabel("error (m/s)")
        ax.grid(alpha=0.3, axis="y")
        ax.legend(loc="upper left")
        counts = ax.twinx()
        counts.plot(x, [row["count"] for row in rows], "s--", color="0.5", ms=3)
        counts.set_ylabel("samples", color="0.4")
    fig.suptitle(title or "test error breakdown")
    fig.tight_layout()
    return _save(fig, path)


def _save(fig: matplotlib.figure.Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
