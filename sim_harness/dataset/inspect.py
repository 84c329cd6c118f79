"""`swarm-sim dataset inspect`: what a dataset holds, as text and two figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sim_harness.dataset.spec import SPLITS, TERMINATIONS
from sim_harness.dataset.store import Dataset
from sim_harness.errors import DatasetError

AXES = ("x (forward)", "y (left)", "z (up)")


def describe(dataset: Dataset) -> str:
    """Counts, split sizes, termination reasons and target statistics, as aligned text."""
    m = dataset.manifest
    spec = m["spec"]
    lines = [
        f"dataset {dataset.root} (id {m['id']}, content {m['content_id']})",
        f"  {spec['n_agents']} agents, seed {spec['seed']}, cone {spec['cone_half_angle_deg']} deg "
        f"x {spec['cone_length_mps']} m/s, shard {spec['shard_index']}/{spec['shard_count']}",
        f"  pixel mean {m['pixel_mean']:.2f}, std {m['pixel_std']:.2f} (training split)",
        "",
        f"  {'split':6s} {'samples':>9s} {'runs':>6s}  "
        + "  ".join(f"{t:>10s}" for t in TERMINATIONS),
    ]
    for split in SPLITS:
        info = m["splits"][split]
        reasons = "  ".join(f"{info['terminations'][t]:>10d}" for t in TERMINATIONS)
        lines.append(f"  {split:6s} {info['n_samples']:>9d} {info['n_runs']:>6d}  {reasons}")
    lines += ["", "  targets (body FLU, m/s):  mean / std / min / max per axis"]
    for split in SPLITS:
        s = m["target_stats"][split]
        cells = [
            f"{s['mean'][a]:+.3f} / {s['std'][a]:.3f} / {s['min'][a]:+.2f} / {s['max'][a]:+.2f}"
            for a in range(3)
        ]
        lines.append(f"  {split:6s} " + "   ".join(cells))
    return "\n".join(lines)


def save_target_histograms(dataset: Dataset, path: Path) -> Path:
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.2), constrained_layout=True)
    for split in SPLITS:
        targets = dataset.split(split).targets
        for a, ax in enumerate(axes):
            lo, hi = np.percentile(targets[:, a], [0.5, 99.5]) if len(targets) else (0, 1)
            ax.hist(
                np.clip(targets[:, a], lo, hi), bins=60, histtype="step", density=True, label=split
            )
    for a, ax in enumerate(axes):
        ax.set_xlabel(f"target {AXES[a]} [m/s]")
        ax.set_yscale("log")
    axes[0].set_ylabel("density")
    axes[0].legend()
    fig.suptitle("Teacher's Reynolds command in the body frame (clipped to the 0.5-99.5 % range)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def save_sample_grid(dataset: Dataset, path: Path, n: int = 8, seed: int = 0) -> Path:
    split = dataset.split("train")
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(split.n_samples, size=min(n, split.n_samples), replace=False))
    meta = split.meta
    images = split.read_images(picks.tolist())  # no image cache written into the dataset
    fig, axes = plt.subplots(len(picks), 1, figsize=(12, 1.45 * len(picks)), squeeze=False)
    for ax, i, image in zip(axes[:, 0], picks, images, strict=True):
        ax.imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        t = split.targets[i]
        ax.set_title(
            f"run {meta['run'][i]}, agent {meta['agent'][i]}, t = {meta['time_s'][i]:.1f} s, "
            f"{meta['n_neighbours'][i]} neighbours, nearest {meta['nearest_m'][i]:.2f} m, "
            f"target ({t[0]:+.2f}, {t[1]:+.2f}, {t[2]:+.2f}) m/s",
            fontsize=8,
        )
        for k in range(1, 6):
            ax.axvline(64 * k - 0.5, color="tab:blue", lw=0.6)
        ax.set_xticks([32 + 64 * k for k in range(6)])
        ax.set_xticklabels(["front", "right", "back", "left", "up", "down"], fontsize=7)
        ax.set_yticks([])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def inspect_dataset(dataset: Dataset, out: Path) -> dict[str, Any]:
    """Print-ready text plus the two figures written into `out` (never the dataset folder)."""
    root = dataset.root.resolve()
    if out.resolve() == root or root in out.resolve().parents:
        raise DatasetError(
            f"out: {out} is inside the dataset {dataset.root}; inspect writes its figures "
            "elsewhere (default runs/inspect/<dataset name>)"
        )
    return {
        "text": describe(dataset),
        "histogram": save_target_histograms(dataset, out / "targets_hist.png"),
        "samples": save_sample_grid(dataset, out / "samples.png"),
    }
