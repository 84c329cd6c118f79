"""Flight scenarios of the paper: common goal, opposing goals, self-propelled.

Geometry (world ENU, metres):
- Agents spawn in a cube of side `spawn_side_m` centred on `SPAWN_CENTER` (5 m above the ground so
  the whole cube is airborne), pairwise at least `spawn_min_separation_m` apart (paper: 4 m cube,
  1.5 m). The paper's density is kept for larger flocks: the default side grows as
  4 m * (N / 9)^(1/3) once N > 9 (random packing of 30 agents into 4 m would often be impossible).
- The common migration point lies `goal_distance_m` (default 30 m) east of the spawn centre, at the
  same altitude: at the migration gain of 1 m/s the flock needs about half a minute.
- Opposing goals: the first round(5N/9) agents (5 of 9) go to the common point, the others to the
  point on the opposite side of the spawn centre.
- Self-propelled: no migration point at all.

"The flock has arrived" when, for every goal, the centroid of the agents assigned to it is within
`arrival_radius_m` (default 2 m) of it. For opposing goals only the majority group's goal counts,
as in the paper (the flock stays together and drifts towards the larger group's waypoint). A
self-propelled flock never arrives; its runs end at the time limit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.flocking import FlockingParams
from companion.validation import require_int_range, require_positive, require_range
from sim_harness.errors import ConfigError

FloatArray = NDArray[np.float64]

SCENARIOS = ("common", "opposing", "self-propelled")
SPAWN_CENTER: tuple[float, float, float] = (0.0, 0.0, 5.0)
PAPER_SPAWN_SIDE_M = 4.0
PAPER_N = 9
DEFAULT_DURATION_S = {"common": 90.0, "opposing": 60.0, "self-propelled": 30.0}


@dataclass(frozen=True)
class ScenarioConfig:
    """What defines a scenario; validated on creation."""

    name: str = "common"
    n_agents: int = 9
    seed: int = 0
    flocking: FlockingParams = field(default_factory=FlockingParams)
    goal_distance_m: float = 30.0
    spawn_side_m: float | None = None  # None: 4 m, grown with N above 9 to keep the density
    spawn_min_separation_m: float = 1.5
    arrival_radius_m: float = 2.0
    duration_s: float | None = None  # time limit; None: DEFAULT_DURATION_S[name]

    def __post_init__(self) -> None:
        if self.name not in SCENARIOS:
            raise ConfigError(
                f"scenario: unknown name {self.name!r}; choose one of {', '.join(SCENARIOS)}"
            )
        require_int_range("scenario.n_agents", self.n_agents, 1, 1000)
        require_int_range("scenario.seed", self.seed, 0)
        require_positive("scenario.goal_distance_m", self.goal_distance_m)
        if self.spawn_side_m is not None:
            require_positive("scenario.spawn_side_m", self.spawn_side_m)
        require_range("scenario.spawn_min_separation_m", self.spawn_min_separation_m, 0.0)
        require_positive("scenario.arrival_radius_m", self.arrival_radius_m)
        if self.duration_s is not None:
            require_range(
                "scenario.duration_s", self.duration_s, 0.0, 86_400.0, low_inclusive=False
            )

    @property
    def spawn_side(self) -> float:
        if self.spawn_side_m is not None:
            return self.spawn_side_m
        return PAPER_SPAWN_SIDE_M * max(1.0, self.n_agents / PAPER_N) ** (1.0 / 3.0)

    @property
    def time_limit_s(self) -> float:
        return self.duration_s if self.duration_s is not None else DEFAULT_DURATION_S[self.name]


@dataclass(frozen=True)
class Scenario:
    """A concrete, seeded scenario: initial positions and per-agent migration points."""

    config: ScenarioConfig
    initial_pos_world_enu: FloatArray  # (N, 3)
    initial_yaw_rad: FloatArray  # (N,)
    migration_points: FloatArray  # (N, 3); NaN rows: no migration point
    groups: NDArray[np.int64]  # (N,) index into `goals`; -1 without a goal
    goals: FloatArray  # (G, 3) distinct migration points
    arrival_goals: NDArray[np.int64]  # indices of the goals whose arrival ends the run

    @property
    def n_agents(self) -> int:
        return self.config.n_agents

    @property
    def has_goal(self) -> bool:
        return len(self.arrival_goals) > 0


def spawn_positions(
    rng: np.random.Generator,
    n: int,
    center: tuple[float, float, float],
    side_m: float,
    min_separation_m: float,
    max_tries: int = 200_000,
) -> FloatArray:
    """N points uniform in a cube, pairwise >= `min_separation_m` (sequential rejection)."""
    points = np.empty((n, 3))
    placed = 0
    tries = 0
    while placed < n:
        tries += 1
        if tries > max_tries:
            raise ConfigError(
                f"scenario.spawn_side_m: could not place {n} agents {min_separation_m:g} m apart "
                f"in a {side_m:g} m cube; enlarge the cube or lower the separation"
            )
        candidate = np.asarray(center) + rng.uniform(-side_m / 2, side_m / 2, size=3)
        if (
            placed
            and np.min(np.linalg.norm(points[:placed] - candidate, axis=1)) < min_separation_m
        ):
            continue
        points[placed] = candidate
        placed += 1
    return points


def build_scenario(config: ScenarioConfig) -> Scenario:
    """Sample the scenario's initial state from its seed (same config -> same scenario)."""
    rng = np.random.default_rng(config.seed)
    n = config.n_agents
    center = np.asarray(SPAWN_CENTER)
    pos = spawn_positions(rng, n, SPAWN_CENTER, config.spawn_side, config.spawn_min_separation_m)
    yaw = rng.uniform(-np.pi, np.pi, size=n)
    east = np.array([config.goal_distance_m, 0.0, 0.0])
    if config.name == "common":
        goals = (center + east)[None, :]
        groups = np.zeros(n, dtype=np.int64)
        arrival = np.array([0])
    elif config.name == "opposing":
        goals = np.stack([center + east, center - east])
        n_first = max(1, round(5 * n / 9)) if n > 1 else 1
        groups = np.where(np.arange(n) < n_first, 0, 1).astype(np.int64)
        majority = int(np.argmax(np.bincount(groups, minlength=2)))
        arrival = np.array([majority])
    else:
        goals = np.empty((0, 3))
        groups = np.full(n, -1, dtype=np.int64)
        arrival = np.array([], dtype=np.int64)
    migration = np.full((n, 3), np.nan)
    has_goal = groups >= 0
    migration[has_goal] = goals[groups[has_goal]]
    return Scenario(config, pos, yaw, migration, groups, goals, arrival.astype(np.int64))
