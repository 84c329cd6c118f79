"""Rendering what each drone's six cameras see, behind a small interface.

`Renderer.render(world, pos, q, agents)` returns one 64x384 uint8 grayscale strip per requested
agent, laid out as `companion.camera.layout` defines. `PyBulletRenderer` draws the drones with
pybullet's CPU TinyRenderer (headless, no shadows) and composites them over the analytic ground and
sky of `sim_harness.sim.scene` using TinyRenderer's depth buffer. The observing drone's own body is
moved out of the scene while its views are rendered (the paper's cameras see past their own
propellers).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.camera.layout import FACE_SIZE_PX, FACES, FOV_DEG, stitch
from companion.frames import quat_to_rotmat
from sim_harness.sim.pybullet_import import pb
from sim_harness.sim.scene import Environment, SceneSpec
from sim_harness.sim.world import World

_PARKED = (0.0, 0.0, -1000.0)  # where the observer's own body waits during its renders
_GRAY_WEIGHTS = np.array([0.299, 0.587, 0.114])  # ITU-R BT.601 luma


class Renderer(Protocol):
    """Renders every requested agent's six views, stitched: (K, 64, 384) uint8."""

    def render(
        self,
        world: World,
        pos_world_enu: ArrayLike,
        q_world_body: ArrayLike,
        agents: Sequence[int] | None = None,
    ) -> NDArray[np.uint8]: ...


def camera_poses(
    pos_world_enu: ArrayLike, q_world_body: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World positions, optical axes and up vectors of every agent's cameras: each (N, 6, 3)."""
    pos = np.asarray(pos_world_enu, dtype=np.float64)
    rot = quat_to_rotmat(q_world_body)  # (N, 3, 3)
    offsets = np.array([f.position_body_flu for f in FACES])  # (6, 3)
    axes = np.array([f.axis_body_flu for f in FACES])
    ups = np.array([f.up_body_flu for f in FACES])
    eye = pos[:, None, :] + np.einsum("nij,fj->nfi", rot, offsets)
    return eye, np.einsum("nij,fj->nfi", rot, axes), np.einsum("nij,fj->nfi", rot, ups)


class PyBulletRenderer:
    """pybullet TinyRenderer (CPU, headless), 64x64 per face, grayscale."""

    def __init__(
        self, near_m: float = 0.05, far_m: float = 120.0, scene: SceneSpec | None = None
    ) -> None:
        self.near_m = near_m
        self.far_m = far_m
        self.environment = Environment(scene or SceneSpec())
        self._projection = pb.computeProjectionMatrixFOV(FOV_DEG, 1.0, near_m, far_m)

    def _render_face(
        self,
        world: World,
        eye: NDArray[np.float64],
        axis: NDArray[np.float64],
        up: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Drones' gray levels and where a drone was drawn, each (64, 64)."""
        cid = world.client_id
        view = pb.computeViewMatrix(
            eye.tolist(), (eye + axis).tolist(), up.tolist(), physicsClientId=cid
        )
        _, _, rgba, depth, _ = pb.getCameraImage(
            FACE_SIZE_PX,
            FACE_SIZE_PX,
            view,
            self._projection,
            shadow=0,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_NO_SEGMENTATION_MASK,
            physicsClientId=cid,
        )
        rgb = np.asarray(rgba, dtype=np.float64).reshape(FACE_SIZE_PX, FACE_SIZE_PX, 4)[..., :3]
        hit = np.asarray(depth).reshape(FACE_SIZE_PX, FACE_SIZE_PX) < 1.0
        return rgb @ _GRAY_WEIGHTS, hit

    def render(
        self,
        world: World,
        pos_world_enu: ArrayLike,
        q_world_body: ArrayLike,
        agents: Sequence[int] | None = None,
    ) -> NDArray[np.uint8]:
        pos = np.asarray(pos_world_enu, dtype=np.float64)
        q = np.asarray(q_world_body, dtype=np.float64)
        chosen = list(range(world.n_agents)) if agents is None else list(agents)
        world.set_poses(pos, q)
        eyes, axes, ups = camera_poses(pos, q)
        out = self.environment.shade(eyes[chosen], quat_to_rotmat(q[chosen]))
        cid = world.client_id
        for k, agent in enumerate(chosen):
            body = world.body_ids[agent]
            pb.resetBasePositionAndOrientation(body, _PARKED, (0, 0, 0, 1), physicsClientId=cid)
            try:
                for f in range(6):
                    gray, hit = self._render_face(
                        world, eyes[agent, f], axes[agent, f], ups[agent, f]
                    )
                    out[k, f][hit] = gray[hit]
            finally:
                w, x, y, z = q[agent]
                pb.resetBasePositionAndOrientation(
                    body, pos[agent].tolist(), (x, y, z, w), physicsClientId=cid
                )
        return stitch(np.clip(np.rint(out), 0, 255).astype(np.uint8))
