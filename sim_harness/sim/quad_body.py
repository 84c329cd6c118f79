"""The quadrotor's shape in pybullet: a central body, four arms in X configuration, four rotors.

About 0.5 m across the rotor tips (like the 450-class frames the paper's Gazebo drones resemble),
1.5 kg. One pybullet body per drone: a compound collision shape (body box, arm boxes, rotor
cylinders) for contacts, and one triangle mesh of the same parts for rendering, coloured through a
small palette texture. A single mesh per drone renders about 3.5x faster in TinyRenderer than one
link per part (the renderer's cost grows with the number of visual shapes), and the palette keeps
every part's colour (FACTS.md: colours passed in a multi-shape call may be ignored).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.validation import require_positive
from sim_harness.sim.pybullet_import import pb

# Palette texture: one 4-pixel-wide column per part colour; u picks the column's centre.
PALETTE_WIDTH_PX = 16
_PART_U = {"body": 2 / 16, "arm": 6 / 16, "rotor": 10 / 16}
_ROTOR_SEGMENTS = 10


@dataclass(frozen=True)
class QuadGeometry:
    """Dimensions in metres, masses in kilograms, colours as RGB in [0, 1]."""

    body_half_extents_m: tuple[float, float, float] = (0.07, 0.07, 0.03)
    arm_length_m: float = 0.18  # body centre to rotor axis
    arm_half_width_m: float = 0.012
    rotor_radius_m: float = 0.065
    rotor_thickness_m: float = 0.01
    rotor_height_m: float = 0.035  # rotor plane above the body centre
    body_mass_kg: float = 1.1
    arm_mass_kg: float = 0.06
    rotor_mass_kg: float = 0.04
    # Dark parts stand out against both the bright sky and the mid-gray ground (sim.scene).
    body_rgb: tuple[float, float, float] = (0.55, 0.08, 0.07)
    arm_rgb: tuple[float, float, float] = (0.10, 0.10, 0.12)
    rotor_rgb: tuple[float, float, float] = (0.16, 0.16, 0.18)

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

    def palette_rgb_u8(self) -> NDArray[np.uint8]:
        """The palette texture (4 x 16 x 3, RGB) whose columns colour the mesh's parts."""
        pal = np.zeros((4, PALETTE_WIDTH_PX, 3), dtype=np.uint8)
        for k, rgb in enumerate((self.body_rgb, self.arm_rgb, self.rotor_rgb)):
            pal[:, 4 * k : 4 * k + 4] = np.rint(np.asarray(rgb) * 255).astype(np.uint8)
        return pal

    def arm_yaws_rad(self) -> list[float]:
        """Directions of the four arms in the body frame (X configuration)."""
        return [math.pi / 4 + k * math.pi / 2 for k in range(4)]


class _Mesh:
    """Flat-shaded triangle soup being assembled: vertices, normals, uvs, indices."""

    def __init__(self) -> None:
        self.vertices: list[list[float]] = []
        self.normals: list[list[float]] = []
        self.uvs: list[list[float]] = []
        self.indices: list[int] = []

    def add(self, verts: NDArray[np.float64], normals: NDArray[np.float64], u: float) -> int:
        base = len(self.vertices)
        self.vertices += verts.tolist()
        self.normals += normals.tolist()
        self.uvs += [[u, 0.5]] * len(verts)
        return base

    def box(self, center: NDArray[np.float64], half: NDArray[np.float64], yaw: float, u: float):
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        for axis in range(3):
            for sign in (-1.0, 1.0):
                n = np.zeros(3)
                n[axis] = sign
                a = np.roll(n, 1) * sign  # two tangents with a x b = n
                b = np.cross(n, a)
                corners = np.array([-a - b, a - b, a + b, -a + b]) + n
                verts = (corners * half) @ rot.T + center
                base = self.add(verts, np.tile(rot @ n, (4, 1)), u)
                self.indices += [base, base + 1, base + 2, base, base + 2, base + 3]

    def cylinder(self, center: NDArray[np.float64], radius: float, height: float, u: float):
        ang = 2 * np.pi * np.arange(_ROTOR_SEGMENTS) / _ROTOR_SEGMENTS
        ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
        for sign in (-1.0, 1.0):
            rim = center + ring * radius + [0.0, 0.0, sign * height / 2]
            verts = np.vstack([center + [0.0, 0.0, sign * height / 2], rim])
            base = self.add(verts, np.tile([0.0, 0.0, sign], (len(verts), 1)), u)
            for k in range(_ROTOR_SEGMENTS):
                i1, i2 = base + 1 + k, base + 1 + (k + 1) % _ROTOR_SEGMENTS
                self.indices += [base, i1, i2] if sign > 0 else [base, i2, i1]
        for k in range(_ROTOR_SEGMENTS):
            k2 = (k + 1) % _ROTOR_SEGMENTS
            low = center - [0.0, 0.0, height / 2]
            high = center + [0.0, 0.0, height / 2]
            verts = np.array(
                [
                    low + ring[k] * radius,
                    low + ring[k2] * radius,
                    high + ring[k2] * radius,
                    high + ring[k] * radius,
                ]
            )
            normals = np.array([ring[k], ring[k2], ring[k2], ring[k]])
            base = self.add(verts, normals, u)
            self.indices += [base, base + 1, base + 2, base, base + 2, base + 3]


def quad_mesh(g: QuadGeometry) -> _Mesh:
    """The drone as one triangle mesh in its body frame (FLU), parts coloured via the palette."""
    mesh = _Mesh()
    mesh.box(np.zeros(3), np.array(g.body_half_extents_m), 0.0, _PART_U["body"])
    arm_half = np.array([g.arm_length_m / 2, g.arm_half_width_m, g.arm_half_width_m])
    for yaw in g.arm_yaws_rad():
        direction = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        mesh.box(direction * g.arm_length_m / 2, arm_half, yaw, _PART_U["arm"])
        rotor_centre = direction * g.arm_length_m + [0.0, 0.0, g.rotor_height_m]
        mesh.cylinder(rotor_centre, g.rotor_radius_m, g.rotor_thickness_m, _PART_U["rotor"])
    return mesh


def create_quadrotor(
    client_id: int,
    geometry: QuadGeometry,
    palette_texture_id: int,
    position: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> int:
    """Create one quadrotor body in world `client_id`; returns its body unique id.

    `palette_texture_id` is `geometry.palette_rgb_u8()` loaded as a texture in that world.
    """
    g = geometry
    cid = {"physicsClientId": client_id}
    arm_half = (g.arm_length_m / 2, g.arm_half_width_m, g.arm_half_width_m)
    types, halves, radii, lengths, positions, orientations = (
        [pb.GEOM_BOX],
        [g.body_half_extents_m],
        [0.0],
        [0.0],
        [(0.0, 0.0, 0.0)],
        [(0.0, 0.0, 0.0, 1.0)],
    )
    for yaw in g.arm_yaws_rad():
        c, s = math.cos(yaw), math.sin(yaw)
        types += [pb.GEOM_BOX, pb.GEOM_CYLINDER]
        halves += [arm_half, (0.0, 0.0, 0.0)]
        radii += [0.0, g.rotor_radius_m]
        lengths += [0.0, g.rotor_thickness_m]
        positions += [
            (c * g.arm_length_m / 2, s * g.arm_length_m / 2, 0.0),
            (c * g.arm_length_m, s * g.arm_length_m, g.rotor_height_m),
        ]
        orientations += [pb.getQuaternionFromEuler((0.0, 0.0, yaw)), (0.0, 0.0, 0.0, 1.0)]
    collision = pb.createCollisionShapeArray(
        shapeTypes=types,
        halfExtents=halves,
        radii=radii,
        lengths=lengths,
        collisionFramePositions=positions,
        collisionFrameOrientations=orientations,
        **cid,
    )
    mesh = quad_mesh(g)
    visual = pb.createVisualShape(
        pb.GEOM_MESH,
        vertices=mesh.vertices,
        indices=mesh.indices,
        uvs=mesh.uvs,
        normals=mesh.normals,
        **cid,
    )
    body = int(
        pb.createMultiBody(
            baseMass=g.mass_kg,
            baseCollisionShapeIndex=collision,
            baseVisualShapeIndex=visual,
            basePosition=position,
            **cid,
        )
    )
    pb.changeVisualShape(
        body, -1, textureUniqueId=palette_texture_id, rgbaColor=(1.0, 1.0, 1.0, 1.0), **cid
    )
    return body
