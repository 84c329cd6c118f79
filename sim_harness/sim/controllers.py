"""The controller interface of a rollout, and the position-based teacher.

A controller receives, per agent, only what that agent may know:

- `OwnState`: its own position, velocity, attitude and migration point (row i is agent i's);
- the senses it declares in `senses`, and only those: `"neighbours"` gives each agent the offsets
  to the agents within its perception radius (a perfect range sensor, the paper's position-based
  baseline); `"cameras"` gives each agent its own 64x384 uint8 camera image, rendered by the
  rollout at capture time (the control tick) from that agent's pose and attitude.

It returns world-ENU velocity setpoints for all agents in one call, shape (N, 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from companion.flocking import FlockingParams, command_from_offsets

FloatArray = NDArray[np.float64]

SENSE_NEIGHBOURS = "neighbours"
SENSE_CAMERAS = "cameras"


@dataclass(frozen=True)
class OwnState:
    """What each agent knows about itself; every array's first axis is the agent."""

    time_s: float
    pos_world_enu: FloatArray  # (N, 3) m
    vel_world_enu: FloatArray  # (N, 3) m/s
    q_world_body: FloatArray  # (N, 4) wxyz, body FLU -> world ENU
    migration_point_world_enu: FloatArray  # (N, 3) m; NaN rows: no migration point


@dataclass(frozen=True)
class NeighbourSensing:
    """Offsets r_ij = p_j - p_i (world ENU) from agent i to the agents it perceives."""

    offsets_world_enu: FloatArray  # (N, N, 3); rows of unperceived agents are zero
    perceived: NDArray[np.bool_]  # (N, N); False on the diagonal and beyond the range


@dataclass(frozen=True)
class Observation:
    """One control step's inputs; a sense the controller did not declare is None."""

    own: OwnState
    neighbours: NeighbourSensing | None = None
    images: NDArray[np.uint8] | None = None  # (N, 64, 384) row i: agent i's stitched views


class Controller(Protocol):
    """Computes every agent's world-ENU velocity setpoint from its own observations."""

    name: str
    senses: frozenset[str]

    def reset(self, n_agents: int) -> None:
        """Forget any state from a previous run (called before each rollout)."""

    def command(self, observation: Observation) -> FloatArray:
        """Velocity setpoints (N, 3), world ENU, m/s."""
        ...


def sense_neighbours(pos_world_enu: FloatArray, range_m: float) -> NeighbourSensing:
    """Offsets each agent perceives within `range_m` (ground truth, no noise)."""
    offsets = pos_world_enu[None, :, :] - pos_world_enu[:, None, :]
    d2 = np.einsum("ijk,ijk->ij", offsets, offsets)
    perceived = d2 < range_m**2
    np.fill_diagonal(perceived, False)
    return NeighbourSensing(np.where(perceived[..., None], offsets, 0.0), perceived)


class TeacherController:
    """The paper's position-based flocking law, fed with perceived neighbour offsets."""

    name = "teacher"
    senses = frozenset({SENSE_NEIGHBOURS})

    def __init__(self, params: FlockingParams) -> None:
        self.params = params

    def reset(self, n_agents: int) -> None:
        del n_agents  # stateless

    def command(self, observation: Observation) -> FloatArray:
        sensing = observation.neighbours
        if sensing is None:
            raise ValueError("the teacher needs the 'neighbours' sense")
        own = observation.own
        return command_from_offsets(
            sensing.offsets_world_enu,
            sensing.perceived,
            own.pos_world_enu,
            own.migration_point_world_enu,
            self.params,
        ).final
