"""The pybullet world: a headless DIRECT client holding N quadrotor bodies.

Every pybullet call names its `physicsClientId`, so several worlds run side by side in one process.
The bodies are placed from the vehicle model's state each physics step (`set_poses`); the world
reports physical contacts between drones (geometry overlap of body, arms or rotors).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import TracebackType

import numpy as np
from numpy.typing import ArrayLike

from companion.validation import require_int_range
from sim_harness.errors import ConfigError, SimError
from sim_harness.sim.pybullet_import import pb
from sim_harness.sim.quad_body import QuadGeometry, create_quadrotor
from sim_harness.sim.scene import load_texture


@dataclass(frozen=True)
class SimRates:
    """Physics and control rates in Hz; the physics rate must be a multiple of the control rate."""

    physics_hz: int = 100
    control_hz: int = 10

    def __post_init__(self) -> None:
        require_int_range("rates.physics_hz", self.physics_hz, 1, 10_000)
        require_int_range("rates.control_hz", self.control_hz, 1, 1_000)
        if self.physics_hz % self.control_hz:
            raise ConfigError(
                f"rates.physics_hz: {self.physics_hz} Hz must be a whole multiple of "
                f"rates.control_hz = {self.control_hz} Hz"
            )

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return self.physics_hz // self.control_hz

    @property
    def physics_dt_s(self) -> float:
        return 1.0 / self.physics_hz

    @property
    def control_dt_s(self) -> float:
        return 1.0 / self.control_hz


class World:
    """A pybullet world holding N quadrotors; use as a context manager (or call `close`)."""

    def __init__(self, n_agents: int, geometry: QuadGeometry | None = None) -> None:
        require_int_range("n_agents", n_agents, 1)
        self.geometry = geometry or QuadGeometry()
        self.client_id: int = pb.connect(pb.DIRECT)
        if self.client_id < 0:
            raise SimError("could not start a pybullet DIRECT client")
        cid = {"physicsClientId": self.client_id}
        pb.setGravity(0.0, 0.0, -9.81, **cid)
        palette = load_texture(self.client_id, self.geometry.palette_rgb_u8())
        self.body_ids: list[int] = [
            create_quadrotor(self.client_id, self.geometry, palette, (3.0 * i, 0.0, 1.0))
            for i in range(n_agents)
        ]
        self._agent_of_body = {body: i for i, body in enumerate(self.body_ids)}
        self._closed = False

    @property
    def n_agents(self) -> int:
        return len(self.body_ids)

    def set_poses(self, pos_world_enu: ArrayLike, q_world_body: ArrayLike) -> None:
        """Place every drone: positions (N, 3) m and attitudes (N, 4) wxyz, world ENU."""
        pos = np.asarray(pos_world_enu, dtype=np.float64)
        q = np.asarray(q_world_body, dtype=np.float64)
        for body, p, (w, x, y, z) in zip(self.body_ids, pos.tolist(), q.tolist(), strict=True):
            pb.resetBasePositionAndOrientation(
                body, p, (x, y, z, w), physicsClientId=self.client_id
            )

    def may_touch(self, pos_world_enu: ArrayLike) -> bool:
        """False when no pair is within twice the bounding radius (no contact is possible)."""
        if self.n_agents < 2:
            return False
        pos = np.asarray(pos_world_enu, dtype=np.float64)
        diff = pos[:, None, :] - pos[None, :, :]
        d2 = np.einsum("ijk,ijk->ij", diff, diff)
        np.fill_diagonal(d2, np.inf)
        return bool(d2.min() <= (2.0 * self.geometry.bounding_radius_m) ** 2)

    def contacts(self, pos_world_enu: ArrayLike, q_world_body: ArrayLike) -> list[tuple[int, int]]:
        """Agent index pairs (i < j) whose bodies touch at these poses, sorted.

        Moves the bodies to these poses and asks pybullet; callers on a hot path ask the cheap
        `may_touch` first.
        """
        self.set_poses(pos_world_enu, q_world_body)
        pb.performCollisionDetection(physicsClientId=self.client_id)
        pairs: set[tuple[int, int]] = set()
        for point in pb.getContactPoints(physicsClientId=self.client_id):
            a = self._agent_of_body.get(point[1])
            b = self._agent_of_body.get(point[2])
            if a is not None and b is not None and a != b:
                pairs.add((min(a, b), max(a, b)))
        return sorted(pairs)

    def close(self) -> None:
        if not self._closed:
            pb.disconnect(physicsClientId=self.client_id)
            self._closed = True

    def __enter__(self) -> World:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
