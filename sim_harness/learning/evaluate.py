"""Evaluating a policy on a dataset split: MSE, RMSE and R² per axis and overall, errors against
the number of neighbours and the distance to the nearest one, figures.

Axes are the body frame FLU components of the velocity command: x forward, y left, z up (m/s).
R² per axis is `1 - SS_res / SS_tot` around that axis' mean target; overall R² pools the three
axes (`1 - sum SS_res / sum SS_tot`), overall MSE is the mean over all samples and axes.
Per-group errors use the error vector's norm: `rmse_mps = sqrt(mean |e|^2 / 3)` (comparable to the
per-axis RMSE) and `mean_error_mps = mean |e|`.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from sim_harness.learning.batches import SplitArrays, prefetch, sequential_batches
from sim_harness.learning.model import AXES

NEAREST_EDGES_M = (0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 7.0, math.inf)

PolicyModule = Callable[[torch.Tensor], torch.Tensor]


def _module_device(model: PolicyModule) -> torch.device:
    if isinstance(model, torch.nn.Module):
        for tensor in [*model.parameters(), *model.buffers()]:
            return tensor.device
    return torch.device("cpu")


def predict(
    model: PolicyModule,
    images_u8: NDArray[np.uint8],
    batch_size: int = 512,
    device: torch.device | None = None,
) -> NDArray[np.float32]:
    """Body-frame FLU velocity (n, 3) in m/s for uint8 images (n, 64, 384), in eval mode.

    `model` is an eager `DroNet` or an exported TorchScript policy; `device` defaults to the
    model's own.
    """
    if isinstance(model, torch.nn.Module):
        model.eval()
    device = device or _module_device(model)
    n = int(images_u8.shape[0])
    out = np.empty((n, 3), dtype=np.float32)

    def batches() -> Any:
        for rows in sequential_batches(n, batch_size):
            yield rows, torch.from_numpy(np.array(images_u8[rows]))  # a writable copy

    with torch.inference_mode():
        for rows, images in prefetch(batches()):
            out[rows] = model(images.to(device, non_blocking=True)).float().cpu().numpy()
    return out


def regression_metrics(pred: ArrayLike, target: ArrayLike) -> dict[str, Any]:
    """MSE ((m/s)^2), RMSE (m/s), R² per axis and overall; R² is None for a constant target."""
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    if p.shape != t.shape or p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"expected two equal (n>0, 3) arrays, got {p.shape} and {t.shape}")
    n = p.shape[0]
    sse = np.sum((p - t) ** 2, axis=0)
    sst = np.sum((t - t.mean(axis=0)) ** 2, axis=0)

    def r2(res: float, tot: float) -> float | None:
        return None if tot <= 0.0 else float(1.0 - res / tot)

    per_axis = {
        axis: {
            "mse": float(sse[k] / n),
            "rmse": float(math.sqrt(sse[k] / n)),
            "r2": r2(float(sse[k]), float(sst[k])),
        }
        for k, axis in enumerate(AXES)
    }
    overall = {
        "mse": float(sse.sum() / (3 * n)),
        "rmse": float(math.sqrt(sse.sum() / (3 * n))),
        "r2": r2(float(sse.sum()), float(sst.sum())),
    }
    return {"n_samples": n, "per_axis": per_axis, "overall": overall}


def _group_row(label: str, err_sq_norm: NDArray[np.float64], **extra: Any) -> dict[str, Any]:
    count = int(err_sq_norm.size)
    return {
        "label": label,
        **extra,
        "count": count,
        "rmse_mps": float(math.sqrt(err_sq_norm.mean() / 3.0)) if count else None,
        "mean_error_mps": float(np.sqrt(err_sq_norm).mean()) if count else None,
    }


def errors_by_value(err_sq_norm: ArrayLike, values: ArrayLike) -> list[dict[str, Any]]:
    """One row per distinct integer value (e.g. number of neighbours), ascending."""
    e = np.asarray(err_sq_norm, dtype=np.float64)
    v = np.asarray(values).astype(np.int64)
    return [_group_row(str(k), e[v == k], value=int(k)) for k in np.unique(v)]


def errors_by_bin(
    err_sq_norm: ArrayLike, values: ArrayLike, edges: Sequence[float]
) -> list[dict[str, Any]]:
    """One row per bin `[edges[i], edges[i+1])` that holds samples; non-finite values: "none"."""
    e = np.asarray(err_sq_norm, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    rows = []
    for low, high in itertools.pairwise(edges):
        mask = np.isfinite(v) & (v >= low) & (v < high)
        if mask.any():
            finite = math.isfinite(high)
            label = f"{low:g}-{high:g}" if finite else f">={low:g}"
            rows.append(_group_row(label, e[mask], low=low, high=high if finite else None))
    if not np.isfinite(v).all():
        rows.append(_group_row("none", e[~np.isfinite(v)], low=None, high=None))
    return rows


def evaluation_report(
    pred: NDArray[np.float32], target: NDArray[np.float32], meta: dict[str, NDArray[Any]]
) -> dict[str, Any]:
    """Metrics plus the error tables for whichever of "n_neighbours" / "nearest_m" `meta` has."""
    err_sq = np.sum((pred.astype(np.float64) - target) ** 2, axis=1)
    report: dict[str, Any] = {"metrics": regression_metrics(pred, target)}
    if "n_neighbours" in meta:
        report["by_n_neighbours"] = errors_by_value(err_sq, meta["n_neighbours"])
    if "nearest_m" in meta:
        report["by_nearest_m"] = errors_by_bin(err_sq, meta["nearest_m"], NEAREST_EDGES_M)
    return report


def evaluate_split(
    model: PolicyModule,
    split: SplitArrays,
    out_dir: Path | None = None,
    batch_size: int = 512,
    device: torch.device | None = None,
    title: str = "",
) -> dict[str, Any]:
    """Predict a whole split and report; with `out_dir`, also write `metrics.json`,
    `predictions.npz` (pred, target), `pred_vs_target.png` and `error_breakdown.png`."""
    pred = predict(model, split.images, batch_size, device)
    target = np.asarray(split.targets, dtype=np.float32)
    report = evaluation_report(pred, target, dict(split.meta))
    if out_dir is not None:
        from sim_harness.learning.plots import save_error_breakdown, save_pred_vs_target

        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(report, indent=2) + "\n")
        np.savez_compressed(out_dir / "predictions.npz", pred=pred, target=target)
        save_pred_vs_target(pred, target, report["metrics"], out_dir / "pred_vs_target.png", title)
        save_error_breakdown(report, out_dir / "error_breakdown.png", title)
    return report
