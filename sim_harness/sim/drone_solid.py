"""The drone as convex parts: the solid `quad_body.quad_mesh` triangulates, for ray casting.

Five boxes (body, four arms) and four ten-sided prisms (the rotors), each a set of planes
{x: n.x <= offset} in the body frame (FLU), with its palette colour and a bounding sphere; the
rotor sides carry the rim normals that TinyRenderer interpolates between (smooth shading).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sim_harness.sim.quad_body import _PART_U, PALETTE_WIDTH_PX, QuadGeometry

FloatArray = NDArray[np.float64]
_Rim = tuple[FloatArray, FloatArray, FloatArray, FloatArray]  # normals and points of a side's rim
_PLANES_PER_PART = 12
_ROTOR_SIDES = 10  # quad_body._ROTOR_SEGMENTS


@dataclass(frozen=True)
class DroneSolid:
    """The drone as convex parts in its body frame (FLU), padded to `_PLANES_PER_PART` planes.

    `normal` (P, 12, 3) outward unit normals and `offset` (P, 12): the part is {x: n.x <= offset};
    padding planes have n = 0, offset = 1 (always satisfied). `rgb_u8` (P, 3) palette colours.
    Smooth planes (rotor sides) carry the two rim normals their shading interpolates between:
    `rim_a`/`rim_b` (P, 12, 3) unit normals at the rim points `rim_pa`/`rim_pb` (P, 12, 3).
    `part_centre` (P, 3) and `part_radius_m` (P,): a bounding sphere per part.
    """

    normal: FloatArray
    offset: FloatArray
    rgb_u8: NDArray[np.uint8]
    smooth: NDArray[np.bool_]
    rim_a: FloatArray
    rim_b: FloatArray
    rim_pa: FloatArray
    rim_pb: FloatArray
    part_centre: FloatArray
    part_radius_m: FloatArray
    radius_m: float


def drone_solid(g: QuadGeometry) -> DroneSolid:
    """Convex parts of `quad_body.quad_mesh(g)`: the body box, four arm boxes, four rotor prisms."""
    palette = g.palette_rgb_u8()[0]
    rgb = {part: palette[int(u * PALETTE_WIDTH_PX)] for part, u in _PART_U.items()}
    parts: list[tuple[list[FloatArray], list[float], NDArray[np.uint8], list[_Rim] | None]] = []
    spheres: list[tuple[FloatArray, float]] = []

    def box(center: FloatArray, half: FloatArray, yaw: float, colour: NDArray[np.uint8]) -> None:
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        normals, offsets = [], []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                n = sign * rot[:, axis]
                normals.append(n)
                offsets.append(float(n @ center + half[axis]))
        parts.append((normals, offsets, colour, None))
        spheres.append((center, float(np.linalg.norm(half))))

    def prism(center: FloatArray, radius: float, height: float, colour: NDArray[np.uint8]) -> None:
        step = 2 * math.pi / _ROTOR_SIDES
        normals, offsets, rims = [], [], []
        for k in range(_ROTOR_SIDES):
            mid = (k + 0.5) * step
            n = np.array([math.cos(mid), math.sin(mid), 0.0])
            normals.append(n)
            offsets.append(float(n @ center + radius * math.cos(step / 2)))
            a = np.array([math.cos(k * step), math.sin(k * step), 0.0])
            b = np.array([math.cos((k + 1) * step), math.sin((k + 1) * step), 0.0])
            rims.append((a, b, center + radius * a, center + radius * b))
        for sign in (-1.0, 1.0):
            normals.append(np.array([0.0, 0.0, sign]))
            offsets.append(sign * float(center[2]) + height / 2)
        parts.append((normals, offsets, colour, rims))
        spheres.append((center, math.hypot(radius, height / 2)))

    box(np.zeros(3), np.array(g.body_half_extents_m), 0.0, rgb["body"])
    arm_half = np.array([g.arm_length_m / 2, g.arm_half_width_m, g.arm_half_width_m])
    for yaw in g.arm_yaws_rad():
        direction = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        box(direction * g.arm_length_m / 2, arm_half, yaw, rgb["arm"])
    for yaw in g.arm_yaws_rad():
        direction = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        centre = direction * g.arm_length_m + np.array([0.0, 0.0, g.rotor_height_m])
        prism(centre, g.rotor_radius_m, g.rotor_thickness_m, rgb["rotor"])

    n_parts = len(parts)
    normal = np.zeros((n_parts, _PLANES_PER_PART, 3))
    offset = np.ones((n_parts, _PLANES_PER_PART))
    smooth = np.zeros((n_parts, _PLANES_PER_PART), dtype=bool)
    rims = np.zeros((4, n_parts, _PLANES_PER_PART, 3))
    for p, (normals, offsets, _, rim) in enumerate(parts):
        normal[p, : len(normals)] = normals
        offset[p, : len(offsets)] = offsets
        for k, vectors in enumerate(rim or []):
            smooth[p, k] = True
            rims[:, p, k] = vectors
    return DroneSolid(
        normal=normal,
        offset=offset,
        rgb_u8=np.array([colour for _, _, colour, _ in parts], dtype=np.uint8),
        smooth=smooth,
        rim_a=rims[0],
        rim_b=rims[1],
        rim_pa=rims[2],
        rim_pb=rims[3],
        part_centre=np.array([c for c, _ in spheres]),
        part_radius_m=np.array([r for _, r in spheres]),
        radius_m=g.bounding_radius_m,
    )
