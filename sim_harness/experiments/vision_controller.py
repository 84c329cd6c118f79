"""The vision-based controller of the rollout: the exported CNN flies every agent from its images.

Per control step, for all N agents at once:

    images (N, 64, 384) uint8, rendered at capture time      (the rollout's `"cameras"` sense)
    v_body  = CNN(images)                                    one batched call, body FLU, m/s
    v_filt  = low-pass(v_body)                               optional, per agent (off by default)
    v_world = cap(R_world_body(q at capture) v_filt + v_mig, v_max)          world ENU, m/s

The last two lines are `companion.control.LowPassFilter` and `companion.control.compose_velocity`:
the same code the drone runs. The controller declares only the `"cameras"` sense, so the rollout
hands it no neighbour offsets; of its own state it reads each agent's attitude (to rotate), position
and migration point (for the migration term). Row i of the command depends on row i of the inputs
only: nothing about another agent's position or velocity reaches it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from companion.control import LowPassFilter, compose_velocity
from companion.flocking import FlockingParams
from companion.policy import Policy, PolicyConfig
from companion.validation import require_int_range, require_range
from sim_harness.errors import ControllerError
from sim_harness.sim.controllers import SENSE_CAMERAS, Observation

FloatArray = NDArray[np.float64]


class BatchPolicy(Protocol):
    """Maps stitched images (B, 64, 384) uint8 to body-FLU velocities (B, 3) float64 in m/s."""

    def infer_batch(self, images_u8: NDArray[np.uint8]) -> FloatArray: ...


@dataclass(frozen=True)
class VisionControlConfig:
    """The CNN controller's control law. Speeds in m/s; the paper's values are the defaults."""

    k_mig: float = 1.0  # migration speed towards the agent's own migration point
    v_max_mps: float = 2.0  # cap of the final command
    low_pass_cutoff_hz: float | None = None  # first-order low-pass on the CNN output; None: off
    # Sensitivity checks only: add uniform noise in [-j, j] m/s to each CNN output component,
    # seeded per run (`jitter_seed`), to see whether a flight's verdict survives a tiny change
    output_jitter_mps: float = 0.0
    jitter_seed: int = 0

    def __post_init__(self) -> None:
        require_range("vision.output_jitter_mps", self.output_jitter_mps, 0.0, 1.0)
        require_range("vision.k_mig", self.k_mig, 0.0, 20.0)
        require_range("vision.v_max_mps", self.v_max_mps, 0.0, 20.0, low_inclusive=False)
        if self.low_pass_cutoff_hz is not None:
            require_range(
                "vision.low_pass_cutoff_hz",
                self.low_pass_cutoff_hz,
                0.0,
                1000.0,
                low_inclusive=False,
            )

    @classmethod
    def from_flocking(
        cls,
        params: FlockingParams,
        low_pass_cutoff_hz: float | None = None,
        output_jitter_mps: float = 0.0,
        jitter_seed: int = 0,
    ) -> VisionControlConfig:
        """The same migration gain and speed cap as the teacher's flocking parameters."""
        return cls(
            params.k_mig, params.v_max_mps, low_pass_cutoff_hz, output_jitter_mps, jitter_seed
        )


class VisionController:
    """CNN flocking: images in, world-ENU velocity setpoints out, all agents in one batch.

    Args:
        policy: anything with `infer_batch` (e.g. `companion.policy.Policy`); not closed here.
        config: the control law (migration gain, speed cap, low-pass cutoff).
        control_dt_s: the control period in s (the low-pass filter's step).
    """

    name = "cnn"
    senses = frozenset({SENSE_CAMERAS})

    def __init__(
        self, policy: BatchPolicy, config: VisionControlConfig, control_dt_s: float = 0.1
    ) -> None:
        if not (math.isfinite(control_dt_s) and control_dt_s > 0.0):
            raise ValueError(f"control_dt_s must be > 0, got {control_dt_s!r}")
        self.policy = policy
        self.config = config
        self.filter = LowPassFilter(config.low_pass_cutoff_hz, control_dt_s)
        self.last_vel_body_flu: FloatArray | None = None  # (N, 3) the CNN's latest output
        self._inference_s = 0.0
        self._jitter = np.random.default_rng(config.jitter_seed)

    def reset(self, n_agents: int) -> None:
        """Start a new run: filter state from rest, timing from zero."""
        require_int_range("n_agents", n_agents, 1)
        self.filter.reset()
        self.last_vel_body_flu = None
        self._inference_s = 0.0
        self._jitter = np.random.default_rng(self.config.jitter_seed)

    def stage_time_s(self) -> dict[str, float]:
        """Wall time spent in the CNN since `reset` (the rollout adds it to the flight's log)."""
        return {"inference": self._inference_s}

    def command(self, observation: Observation) -> FloatArray:
        """World-ENU velocity setpoints (N, 3) in m/s from each agent's own image and state."""
        images = observation.images
        own = observation.own
        n = own.pos_world_enu.shape[0]
        if images is None:
            raise ControllerError("the CNN controller needs the 'cameras' sense (no images given)")
        if images.shape[0] != n:
            raise ControllerError(f"got {images.shape[0]} images for {n} agents")
        start = time.perf_counter()
        vel_body = np.asarray(self.policy.infer_batch(images), dtype=np.float64)
        self._inference_s += time.perf_counter() - start
        if vel_body.shape != (n, 3):
            raise ControllerError(f"the policy returned shape {vel_body.shape}; expected ({n}, 3)")
        if self.config.output_jitter_mps > 0.0:
            j = self.config.output_jitter_mps
            vel_body = vel_body + self._jitter.uniform(-j, j, size=vel_body.shape)
        self.last_vel_body_flu = vel_body
        vel_filtered = self.filter.step(vel_body)
        return compose_velocity(
            vel_filtered,
            own.q_world_body,
            own.pos_world_enu,
            own.migration_point_world_enu,
            self.config.k_mig,
            self.config.v_max_mps,
        )


def load_policy(
    model_path: Path, threads: int = 1, sha256: str | None = None, graph_fusion: bool = False
) -> Policy:
    """Load and verify an exported policy file for simulation (close it after use).

    Raises `companion.errors.ModelError` when the file is missing, altered or not a policy.
    `threads` sets torch's intra-op threads for the whole process. The simulation runs the graph
    unfused by default (`graph_fusion`, process-wide): the oneDNN Graph fuser compiles a plan per
    input shape during a module's first calls at that shape, which run unfused, so a flight's
    last-bit rounding (and, through the flock's dynamics, its trajectory) would depend on what
    the process flew before. Unfused, a seed gives the same flight in any worker and order; the
    outputs agree with the drone's fused run to about 1e-6 m/s.
    """
    config = PolicyConfig(
        model_path=model_path, sha256=sha256, threads=threads, graph_fusion=graph_fusion
    )
    return Policy.load(config)
