"""The quadrotor's shape in pybullet: a central body, four arms in X configuration, four rotors.

About 0.5 m across the rotor tips (like the 450-class frames the paper's Gazebo drones resemble),
1.5 kg. Every part is its own fixed link so that each keeps its colour (FACTS.md: colours passed in
a multi-shape call may be ignored, and drones then vanish against the ground).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.validation import require_positive
from sim_harness.pybullet_import import pb


@dataclass(frozen=True)
class QuadGeometry:
    """Dimensions in metres, masses in kilograms."""

    body_half_extents_m: tuple[float, float, float] = (0.07, 0.07, 0.03)
    arm_length_m: float = 0.18  # body centre to rotor axis
    arm_half_width_m: float = 0.012
    rotor_radius_m: float = 0.065
    rotor_thickness_m: float = 0.01
    rotor_height_m: float = 0.035  # rotor plane above the body centre
    body_mass_kg: float = 1.1
    arm_mass_kg: float = 0.06
    rotor_mass_kg: float = 0.04
    body_rgba: tuple[float, float, float, float] = (0.85, 0.12, 0.10, 1.0)
    arm_rgba: tuple[float, float, float, float] = (0.10, 0.10, 0.12, 1.0)
    rotor_rgba: tuple[float, float, float, float] = (0.95, 0.55, 0.05, 1.0)

    def __post_init__(self) -> None:
        for name in ("arm_length_m", "arm_half_width_m", "rotor_radius_m", "rotor_thickness_m"):
            require_positive(f"quad.{name}", getattr(self, name))

    @property
    def span_m(self) -> float:
        """Distance between opposite rotor tips."""
        return 2.0 * (self.arm_length_m + self.rotor_radius_m)

    @property
    def mass_kg(self) -> float:
        return self.body_mass_kg + 4 * (self.arm_mass_kg + self.rotor_mass_kg)

    @property
    def bounding_radius_m(self) -> float:
        """Radius of a sphere about the body centre that contains the whole vehicle."""
        return math.hypot(
            self.arm_length_m + self.rotor_radius_m,
            self.rotor_height_m + self.rotor_thickness_m / 2,
        )


def create_quadrotor(
    client_id: int, geometry: QuadGeometry, position: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> int:
    """Create one quadrotor multibody in world `client_id`; returns its body unique id."""
    g = geometry
    cid = {"physicsClientId": client_id}
    body_col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=g.body_half_extents_m, **cid)
    body_vis = pb.createVisualShape(
        pb.GEOM_BOX, halfExtents=g.body_half_extents_m, rgbaColor=g.body_rgba, **cid
    )
    arm_half = (g.arm_length_m / 2, g.arm_half_width_m, g.arm_half_width_m)
    arm_col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=arm_half, **cid)
    arm_vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=arm_half, rgbaColor=g.arm_rgba, **cid)
    rotor_col = pb.createCollisionShape(
        pb.GEOM_CYLINDER, radius=g.rotor_radius_m, height=g.rotor_thickness_m, **cid
    )
    rotor_vis = pb.createVisualShape(
        pb.GEOM_CYLINDER,
        radius=g.rotor_radius_m,
        length=g.rotor_thickness_m,
        rgbaColor=g.rotor_rgba,
        **cid,
    )
    masses, cols, viss, positions, orientations = [], [], [], [], []
    for k in range(4):
        angle = math.pi / 4 + k * math.pi / 2  # X configuration
        c, s = math.cos(angle), math.sin(angle)
        masses.append(g.arm_mass_kg)
        cols.append(arm_col)
        viss.append(arm_vis)
        positions.append((c * g.arm_length_m / 2, s * g.arm_length_m / 2, 0.0))
        orientations.append(pb.getQuaternionFromEuler((0.0, 0.0, angle)))
    for k in range(4):
        angle = math.pi / 4 + k * math.pi / 2
        masses.append(g.rotor_mass_kg)
        cols.append(rotor_col)
        viss.append(rotor_vis)
        positions.append(
            (math.cos(angle) * g.arm_length_m, math.sin(angle) * g.arm_length_m, g.rotor_height_m)
        )
        orientations.append((0.0, 0.0, 0.0, 1.0))
    n = len(masses)
    body = int(
        pb.createMultiBody(
            baseMass=g.body_mass_kg,
            baseCollisionShapeIndex=body_col,
            baseVisualShapeIndex=body_vis,
            basePosition=position,
            linkMasses=masses,
            linkCollisionShapeIndices=cols,
            linkVisualShapeIndices=viss,
            linkPositions=positions,
            linkOrientations=orientations,
            linkInertialFramePositions=[(0.0, 0.0, 0.0)] * n,
            linkInertialFrameOrientations=[(0.0, 0.0, 0.0, 1.0)] * n,
            linkParentIndices=[0] * n,
            linkJointTypes=[pb.JOINT_FIXED] * n,
            linkJointAxis=[(0.0, 0.0, 1.0)] * n,
            **cid,
        )
    )
    # Colours set per link explicitly: multi-shape calls may drop them.
    pb.changeVisualShape(body, -1, rgbaColor=g.body_rgba, **cid)
    for link in range(4):
        pb.changeVisualShape(body, link, rgbaColor=g.arm_rgba, **cid)
        pb.changeVisualShape(body, 4 + link, rgbaColor=g.rotor_rgba, **cid)
    return body
