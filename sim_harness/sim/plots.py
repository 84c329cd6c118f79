"""Figures like the paper's: top-view trajectories, d_min / d_max over time, order over time.

Several runs of one experiment (seeds) are drawn as a mean line with a shaded min-max band;
a single run is drawn as its line.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Rectangle

from sim_harness.sim.metrics import COLLISION_THRESHOLD_M
from sim_harness.sim.rollout import FlightLog
from sim_harness.sim.scenarios import SPAWN_CENTER

GREY = "0.55"


def _agent_colours(n: int) -> list[tuple[float, float, float, float]]:
    cmap = plt.get_cmap("tab10" if n <= 10 else "tab20")
    return [cmap(i % cmap.N) for i in range(n)]


def draw_trajectories(ax: Axes, log: FlightLog, title: str | None = None) -> None:
    """Top view (east, north): one colour per agent; square / triangle / circle at the first /
    middle / last step; spawn area and migration points in grey; the second group dotted."""
    sc = log.scenario
    pos = log.pos_world_enu
    side = sc.config.spawn_side
    ax.add_patch(
        Rectangle(
            (SPAWN_CENTER[0] - side / 2, SPAWN_CENTER[1] - side / 2),
            side,
            side,
            facecolor=GREY,
            alpha=0.25,
            edgecolor=GREY,
            zorder=0,
        )
    )
    for goal in sc.goals:
        ax.plot(goal[0], goal[1], "o", ms=14, color=GREY, alpha=0.6, zorder=1)
    mid = pos.shape[0] // 2
    for i, colour in enumerate(_agent_colours(sc.n_agents)):
        style = ":" if sc.groups[i] == 1 else "-"
        ax.plot(pos[:, i, 0], pos[:, i, 1], style, color=colour, lw=1.3, zorder=2)
        for step, marker in ((0, "s"), (mid, "^"), (-1, "o")):
            ax.plot(
                pos[step, i, 0],
                pos[step, i, 1],
                marker,
                color=colour,
                ms=5,
                mec="k",
                mew=0.4,
                zorder=3,
            )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.grid(alpha=0.3)
    ax.set_title(title or f"{sc.config.name}, {log.controller}: top view")


def _band(ax: Axes, logs: Sequence[FlightLog], attr: str, colour: str, label: str) -> None:
    length = max(log.n_steps for log in logs)
    data = np.full((len(logs), length), np.nan)
    for k, log in enumerate(logs):
        data[k, : log.n_steps] = getattr(log, attr)
    t = np.arange(length) * logs[0].rates.control_dt_s
    with np.errstate(all="ignore"):
        ax.plot(t, np.nanmean(data, axis=0), color=colour, lw=1.6, label=label)
        if len(logs) > 1:
            ax.fill_between(
                t, np.nanmin(data, axis=0), np.nanmax(data, axis=0), color=colour, alpha=0.2, lw=0
            )


def draw_distances(ax: Axes, groups: Mapping[str, Sequence[FlightLog]]) -> None:
    """d_min and d_max over time for each labelled group of runs (e.g. teacher, CNN)."""
    colours = iter(["tab:blue", "tab:orange", "tab:green", "tab:red"])
    for label, logs in groups.items():
        colour = next(colours)
        _band(ax, logs, "d_max_m", colour, f"{label} $d_{{max}}$")
        _band(ax, logs, "d_min_m", colour, f"{label} $d_{{min}}$")
        ax.lines[-1].set_linestyle("--")
    ax.axhline(COLLISION_THRESHOLD_M, color="k", lw=0.8, ls=":", label="collision (1 m)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("inter-agent distance [m]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")


def draw_order(ax: Axes, groups: Mapping[str, Sequence[FlightLog]]) -> None:
    """Order parameter over time for each labelled group of runs."""
    colours = iter(["tab:blue", "tab:orange", "tab:green", "tab:red"])
    for label, logs in groups.items():
        _band(ax, logs, "order", next(colours), label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("order parameter")
    ax.set_ylim(-1.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")


def save_flight_figures(log: FlightLog, out_dir: Path) -> dict[str, Path]:
    """trajectories.png, distances.png, order.png and flight.png (all three side by side)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {
        name: out_dir / f"{name}.png" for name in ("trajectories", "distances", "order", "flight")
    }
    groups = {log.controller: [log]}
    for name, draw in (
        ("trajectories", lambda ax: draw_trajectories(ax, log)),
        ("distances", lambda ax: draw_distances(ax, groups)),
        ("order", lambda ax: draw_order(ax, groups)),
    ):
        fig, ax = plt.subplots(figsize=(6, 4.5), dpi=120)
        draw(ax)
        fig.tight_layout()
        fig.savefig(paths[name])
        plt.close(fig)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6), dpi=110)
    draw_trajectories(axes[0], log)
    draw_distances(axes[1], groups)
    draw_order(axes[2], groups)
    axes[1].set_title("min / max inter-agent distance")
    axes[2].set_title("order parameter")
    fig.tight_layout()
    fig.savefig(paths["flight"])
    plt.close(fig)
    return paths


def save_comparison_figure(
    columns: Mapping[str, Mapping[str, Sequence[FlightLog]]], path: Path, dpi: int = 90
) -> Path:
    """The paper's figure for teacher and CNN side by side: one column per experiment (e.g.
    common, opposing goals); rows: one top view per controller (its first run), then d_min / d_max
    and the order parameter of every controller (mean line, min-max band over runs).

    `columns` maps a column title to {controller label: runs}; every column has the same labels.
    """
    labels = list(next(iter(columns.values())).keys())
    n_rows = len(labels) + 2
    fig, axes = plt.subplots(
        n_rows,
        len(columns),
        figsize=(6.5 * len(columns), 4.2 * n_rows + 1.0),
        dpi=dpi,
        squeeze=False,
        gridspec_kw={"height_ratios": [1.4] * len(labels) + [1, 1]},
    )
    for col, (title, groups) in enumerate(columns.items()):
        for row, label in enumerate(labels):
            runs = groups[label]
            seed = runs[0].scenario.config.seed
            draw_trajectories(axes[row, col], runs[0], title=f"{title}: {label}, seed {seed}")
        draw_distances(axes[len(labels), col], groups)
        draw_order(axes[len(labels) + 1, col], groups)
        counts = sorted({len(v) for v in groups.values()})
        n_runs = "/".join(str(c) for c in counts) + (" run" if counts == [1] else " runs")
        axes[len(labels), col].set_title(f"min / max inter-agent distance ({n_runs} each)")
        axes[len(labels) + 1, col].set_title(f"order parameter ({n_runs} each)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
