"""The real-PX4 swarm's world loop: every drone where its PX4 says, on the 100 Hz grid."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

from sim_harness.hil.camera_side import PoseBoard
from sim_harness.hil.lateness import GridClock, Lateness
from sim_harness.hil.px4_drone import POSE_RATE_HZ
from sim_harness.sim.world import World

if TYPE_CHECKING:
    from sim_harness.hil.px4_swarm import Px4Swarm


class WorldClock(GridClock):
    """The world on the 100 Hz grid: every drone where its PX4 says, to the pose board."""

    def __init__(self, swarm: Px4Swarm, world: World, board: PoseBoard, lateness: Lateness) -> None:
        self.swarm, self.world, self.board, self.lateness = swarm, world, board, lateness
        self.dt_s = swarm.config.rates.physics_dt_s
        self.next_step = time.monotonic()
        self.pose_late_s = swarm.config.late_physics_s + 1.0 / POSE_RATE_HZ
        self.last = swarm._poses(self.next_step)

    def _run_due(self, now: float) -> set[tuple[int, int]]:
        lat, late_s = self.lateness, self.swarm.config.late_physics_s
        touching: set[tuple[int, int]] = set()
        if self.next_step > now:
            return touching
        behind = now - self.next_step
        missed = math.floor(behind / self.dt_s)  # steps not taken: one pose update covers them
        lat.physics_steps += 1 + missed
        stale = self.swarm._pose_age_s(now) > self.pose_late_s
        lat.physics_late += (behind > late_s or stale) + missed
        self.swarm.world_steps_behind += (behind > late_s) + missed
        self.swarm.world_steps_pose_stale += stale
        lat.physics_max_behind_s = max(lat.physics_max_behind_s, behind)
        self.last = pos, _, q = self.swarm._poses(now)
        self.board.write(pos, q)
        if self.world.may_touch(pos):
            touching.update(self.world.contacts(pos, q))
        self.next_step += (1 + missed) * self.dt_s
        return touching
