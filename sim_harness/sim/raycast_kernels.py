"""Compiled loops (numba) for `sim_harness.sim.raycast`: the same arithmetic without temporaries.

Optional: `RaycastRenderer` uses them when numba imports (`pip install numba`), else its numpy
path; both give the same drone pixels (tests/sim_harness/sim/test_raycast.py compares them).

- `shade_environment`: `scene.Environment.shade` per pixel. The ground texture is sampled the way
  `cv2.remap(INTER_LINEAR, BORDER_WRAP)` does (coordinates rounded to 1/32 texel, wrapped); gray
  levels agree with the numpy path to ~0.1 (a few pixels in a thousand round to the next level).
- `cast_drones`: for each (observer face, other drone) pair, the pixels whose ray meets the drone's
  bounding sphere (one column interval per row), each tested against the parts' spheres and slabs;
  the nearest hit per pixel is kept in a depth buffer.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_SIZE_PX, FACES
from sim_harness.sim.scene import Environment

FloatArray = NDArray[np.float64]
_MAX_GROUND_M = 1000.0  # as scene.Environment


def environment(env: Environment, eye: FloatArray, rot: FloatArray) -> NDArray[np.float32]:
    """`env.shade(eye, rot)` compiled: (K, 6, 64, 64) float32."""
    s = env.spec
    if s.ground_texture_px & (s.ground_texture_px - 1):
        raise ValueError(f"scene.ground_texture_px: {s.ground_texture_px} is not a power of two")
    out = np.empty((len(eye), len(FACES), FACE_SIZE_PX * FACE_SIZE_PX), dtype=np.float32)
    shade_environment(
        env._rays_body.reshape(len(FACES), -1, 3),
        eye.astype(np.float32),
        rot.astype(np.float32),
        env._texture,
        s.ground_texture_px / s.ground_tile_m,
        s.ground_mean,
        s.ground_fade_m,
        s.sky_horizon_gray,
        s.sky_zenith_gray,
        _MAX_GROUND_M,
        out,
    )
    return out.reshape(len(eye), len(FACES), FACE_SIZE_PX, FACE_SIZE_PX)


@numba.njit(cache=True, fastmath=True)  # type: ignore[misc]
def shade_environment(
    rays_body: NDArray[np.float32],  # (6, P, 3) unit rays, body frame
    eye: NDArray[np.float32],  # (K, 6, 3)
    rot: NDArray[np.float32],  # (K, 3, 3) body -> world
    texture: NDArray[np.float32],  # (S, S)
    scale: float,  # texels per metre
    mean: float,
    fade_m: float,
    horizon: float,
    zenith: float,
    max_t: float,
    out: NDArray[np.float32],  # (K, 6, P)
) -> None:
    mask = texture.shape[0] - 1  # the texture side is a power of two: wrap by masking
    inv_fade = -1.0 / fade_m
    for k in range(eye.shape[0]):
        r = rot[k]
        for f in range(eye.shape[1]):
            ex, ey, ez = eye[k, f, 0], eye[k, f, 1], eye[k, f, 2]
            for p in range(rays_body.shape[1]):
                bx, by, bz = rays_body[f, p, 0], rays_body[f, p, 1], rays_body[f, p, 2]
                dz = r[2, 0] * bx + r[2, 1] * by + r[2, 2] * bz
                if dz < -1e-6:
                    dx = r[0, 0] * bx + r[0, 1] * by + r[0, 2] * bz
                    dy = r[1, 0] * bx + r[1, 1] * by + r[1, 2] * bz
                    t = min(ez / -dz, max_t)
                    ix = int(np.rint((ex + t * dx) * scale * 32.0))
                    iy = int(np.rint((ey + t * dy) * scale * 32.0))
                    fx, fy = (ix & 31) / 32.0, (iy & 31) / 32.0
                    x0, y0 = (ix >> 5) & mask, (iy >> 5) & mask
                    x1, y1 = (x0 + 1) & mask, (y0 + 1) & mask
                    top = (1.0 - fx) * texture[y0, x0] + fx * texture[y0, x1]
                    bottom = (1.0 - fx) * texture[y1, x0] + fx * texture[y1, x1]
                    texel = (1.0 - fy) * top + fy * bottom
                    out[k, f, p] = mean + (texel - mean) * math.exp(t * inv_fade)
                else:
                    out[k, f, p] = horizon + (zenith - horizon) * min(max(dz, 0.0), 1.0)


@numba.njit(cache=True)  # type: ignore[misc]
def cast_drones(
    centre: FloatArray,  # (T, 3) drone centre in camera coordinates (right, up, forward)
    box: NDArray[np.intp],  # (4, T) first/last column, first/last row
    cam_to_body: FloatArray,  # (T, 3, 3) camera -> drone body
    origin: FloatArray,  # (T, 3) the eye in the drone's body frame
    face_base: NDArray[np.intp],  # (T,) flat index of the face's first pixel
    rays_cam: FloatArray,  # (size * size, 3)
    size: int,  # face side, pixels
    half: float,  # tan(FOV / 2)
    radius: float,
    offset_x: float,
    offset_y: float,
    near: float,
    far: float,
    normal: FloatArray,  # (P, 12, 3)
    offset: FloatArray,  # (P, 12)
    n_planes: NDArray[np.intp],  # (P,) used planes of each part
    part_centre: FloatArray,  # (P, 3)
    part_radius: FloatArray,  # (P,)
    depth: FloatArray,  # (K * 6 * 64 * 64,) inf where no drone yet
    owner: NDArray[np.intp],  # same shape: pair index t of the nearest hit, -1 if none
    part_hit: NDArray[np.intp],
    plane_hit: NDArray[np.intp],
    touched: NDArray[np.intp],  # out: the pixels hit, first `return value` entries
) -> int:
    n_touched = 0
    r2 = radius * radius
    for t in range(centre.shape[0]):
        cx, cy, cz = centre[t, 0], centre[t, 1], centre[t, 2]
        k = cx * cx + cy * cy + cz * cz - r2
        for row in range(box[2, t], box[3, t] + 1):
            v = (1.0 - (row + offset_y) / size * 2.0) * half
            e = v * cy + cz
            a = cx * cx - k
            lo, hi = box[0, t], box[1, t]
            bounded = a < 0.0 and k > 0.0
            if bounded:
                disc = (cx * e) ** 2 - a * (e * e - k * (v * v + 1.0))
                if disc < 0.0 or cx * (-cx * e / a) + e <= 0.0:
                    continue
                root = math.sqrt(disc)
                lo = max(lo, math.ceil(((-cx * e + root) / a / half + 1.0) * size / 2 - offset_x))
                hi = min(hi, math.floor(((-cx * e - root) / a / half + 1.0) * size / 2 - offset_x))
            for col in range(lo, hi + 1):
                pix = row * size + col
                rx, ry, rz = rays_cam[pix, 0], rays_cam[pix, 1], rays_cam[pix, 2]
                if not bounded:
                    b = rx * cx + ry * cy + rz * cz
                    if not ((b * b >= k and b > 0.0) or k < 0.0):
                        continue
                m = cam_to_body[t]
                dx = m[0, 0] * rx + m[0, 1] * ry + m[0, 2] * rz
                dy = m[1, 0] * rx + m[1, 1] * ry + m[1, 2] * rz
                dz = m[2, 0] * rx + m[2, 1] * ry + m[2, 2] * rz
                ox, oy, oz = origin[t, 0], origin[t, 1], origin[t, 2]
                best, best_part, best_plane = np.inf, -1, -1
                for p in range(normal.shape[0]):
                    qx, qy, qz = (
                        ox - part_centre[p, 0],
                        oy - part_centre[p, 1],
                        oz - part_centre[p, 2],
                    )
                    b = qx * dx + qy * dy + qz * dz
                    c = qx * qx + qy * qy + qz * qz - part_radius[p] ** 2
                    if not (b * b >= c and (b < 0.0 or c < 0.0)):
                        continue
                    enter, leave, plane = -np.inf, np.inf, -1
                    for s in range(n_planes[p]):
                        n = normal[p, s]
                        denom = n[0] * dx + n[1] * dy + n[2] * dz
                        num = offset[p, s] - (n[0] * ox + n[1] * oy + n[2] * oz)
                        if denom < 0.0:
                            if num / denom > enter:
                                enter, plane = num / denom, s
                        elif denom > 0.0:
                            leave = min(leave, num / denom)
                        elif num < 0.0:
                            leave = -np.inf
                    if enter <= leave and enter > 0.0 and enter < best:
                        best, best_part, best_plane = enter, p, plane
                if best_part < 0:
                    continue
                z = best * rz
                idx = face_base[t] + pix
                if near <= z <= far and best < depth[idx]:
                    if owner[idx] < 0:
                        touched[n_touched] = idx
                        n_touched += 1
                    depth[idx], owner[idx] = best, t
                    part_hit[idx], plane_hit[idx] = best_part, best_plane
    return n_touched
