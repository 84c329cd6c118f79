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
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from sim_harness.sim.metrics import COLLISION_THRESHOLD_M
from sim_harness.sim.rollout import FlightLog
from sim_harness.sim.scenarios import SPAWN_CENTER

GREY = "0.55"
VIEW_MARGIN_M = 2.0  # top views frame the flock: its trajectories plus this margin, or
VIEW_MARGIN_FRACTION = 0.1  # this fraction of the larger side, whichever is larger
# What the figures' marks mean, for the captions of reports that include them.
TRAJECTORY_KEY = (
    "Top views: one colour per drone; squares, triangles and circles mark its first, middle and "
    "last step; the grey square is the spawn area, grey discs the migration points (an arrow at "
    "the edge points to one outside the view); the second group of opposing goals is dotted"
)
BANDS_KEY = (
    "distance and order panels: the mean over runs as a line (d_max solid, d_min dashed, the "
    "dotted black line the 1 m collision threshold), the min-max range over runs shaded"
)


def _agent_colours(n: int) -> list[tuple[float, float, float, float]]:
    cmap = plt.get_cmap("tab10" if n <= 10 else "tab20")
    return [cmap(i % cmap.N) for i in range(n)]


def _view_box(log: FlightLog) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) east-north corners framing every trajectory and the spawn area, with margin."""
    side = log.scenario.config.spawn_side
    centre = np.asarray(SPAWN_CENTER[:2], dtype=np.float64)
    points = np.concatenate(
        [log.pos_world_enu[:, :, :2].reshape(-1, 2), [centre - side / 2, centre + side / 2]]
    )
    low, high = points.min(axis=0), points.max(axis=0)
    margin = max(VIEW_MARGIN_M, VIEW_MARGIN_FRACTION * float(np.max(high - low)))
    return low - margin, high + margin


def _goal_at_edge(ax: Axes, goal: np.ndarray, low: np.ndarray, high: np.ndarray) -> None:
    """An arrow at the edge of the view pointing towards a migration point outside it."""
    centre, half = (low + high) / 2, (high - low) / 2
    direction = goal[:2] - centre
    t = float(np.min(0.97 * half / np.maximum(np.abs(direction), 1e-9)))
    tip = centre + t * direction
    unit = direction / np.linalg.norm(direction)
    # The label sits inside the view, behind the arrow: right of it for a goal to the west, etc.
    ha = "right" if unit[0] > 0.3 else "left" if unit[0] < -0.3 else "center"
    va = "top" if unit[1] > 0.3 else "bottom" if unit[1] < -0.3 else "center"
    ax.annotate(
        f"goal ({goal[0]:+.0f}, {goal[1]:+.0f}) m",
        xy=(float(tip[0]), float(tip[1])),
        xytext=(float(-28 * unit[0]), float(-28 * unit[1])),
        textcoords="offset points",
        arrowprops={"arrowstyle": "-|>", "color": GREY, "lw": 1.5},
        color="0.3",
        fontsize=7,
        ha=ha,
        va=va,
        zorder=4,
    )


def _trajectory_legend(ax: Axes, two_groups: bool) -> None:
    dark = "0.3"
    handles = [
        Line2D([], [], marker="s", ls="", color=dark, ms=5, label="first step"),
        Line2D([], [], marker="^", ls="", color=dark, ms=5, label="middle step"),
        Line2D([], [], marker="o", ls="", color=dark, ms=5, label="last step"),
        Patch(facecolor=GREY, alpha=0.25, edgecolor=GREY, label="spawn area"),
        Line2D([], [], marker="o", ls="", color=GREY, alpha=0.6, ms=10, label="migration point"),
    ]
    if two_groups:
        handles.append(Line2D([], [], ls=":", color=dark, label="second group (other goal)"))
    ax.legend(handles=handles, fontsize=7, loc="best", framealpha=0.8)


def draw_trajectories(ax: Axes, log: FlightLog, title: str | None = None) -> None:
    """Top view (east, north) framing the flock: one colour per agent; square / triangle / circle
    at the first / middle / last step; spawn area and migration points in grey (an arrow at the
    edge for a point outside the view); the second group dotted; a legend says so."""
    sc = log.scenario
    pos = log.pos_world_enu
    side = sc.config.spawn_side
    low, high = _view_box(log)
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
        if np.all(goal[:2] >= low) and np.all(goal[:2] <= high):
            ax.plot(goal[0], goal[1], "o", ms=14, color=GREY, alpha=0.6, zorder=1)
        else:
            _goal_at_edge(ax, goal, low, high)
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
    ax.update_datalim([(low[0], low[1]), (high[0], high[1])])
    ax.margins(0)  # the view box has its margin; equal aspect widens one side if needed
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.grid(alpha=0.3)
    ax.set_title(title or f"{sc.config.name}, {log.controller}: top view")
    _trajectory_legend(ax, bool(np.any(sc.groups == 1)))


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
