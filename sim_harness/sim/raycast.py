"""A batched ray-cast renderer: every requested agent's six faces in one vectorized numpy pass.

Same scene and camera model as `sim_harness.sim.render.PyBulletRenderer`, without pybullet:

- The environment (ground and sky) is `sim_harness.sim.scene.Environment.shade`, as there.
- Each drone is the solid that `sim_harness.sim.quad_body.quad_mesh` triangulates, as nine convex
  parts (`sim_harness.sim.drone_solid`), so a ray meets a part where the last plane it enters
  precedes the first plane it leaves ("slab" test): 9 parts x at most 12 planes per ray instead of
  220 triangles.
- Culling: per (observer, face, other drone) the drone's bounding sphere is projected to a pixel
  box; only the rays in those boxes that also pass the sphere are tested against its planes.
- Shading copies TinyRenderer's fragment shader as pybullet configures it: palette colour times
  (0.6 ambient + 0.35 diffuse + 0.05 specular^2), per RGB channel truncated to an integer, then the
  same BT.601 gray as `PyBulletRenderer`; the light comes from (-50, 30, 100) (pybullet's default
  for a z-up world). Rotor sides get TinyRenderer's interpolated normals (smooth), the rest flat.
- Sampling: one ray per pixel by default (no anti-aliasing, like TinyRenderer).
  `sample_offset_px` places the sample inside the pixel. The default (0, 1), the pixel's
  bottom-left corner, is where TinyRenderer samples (measured: the two renderers then agree on
  every drone pixel); (0.5, 0.5) would be the pixel centre that `companion.camera.layout` and
  the environment use.
- `supersample=K` (`raycast-aa`: K = 4): the drones are sampled on a K x K grid inside each pixel
  and each pixel gets the mean, as a camera's sensor integrates the light over a pixel's area
  (OpenMV's 64x64 is its sensor's image scaled down). With one ray per pixel a drone further than
  a few metres, thinner than a pixel, falls between the rays: drawn on no pixel at all in about
  half the frames at 5 m (`benchmarks/drone_visibility.py`). The environment is smooth and keeps
  one sample per pixel.
- The observer's own body is not drawn; drones nearer than `near_m` or beyond `far_m` along the
  optical axis are clipped, as TinyRenderer's frustum does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.camera.layout import FACE_SIZE_PX, FACES, FOV_DEG, stitch
from companion.frames import quat_to_rotmat
from companion.validation import require_int_range
from sim_harness.sim.drone_solid import DroneSolid, drone_solid
from sim_harness.sim.quad_body import QuadGeometry
from sim_harness.sim.render import camera_poses
from sim_harness.sim.scene import Environment, SceneSpec
from sim_harness.sim.world import World

try:  # compiled loops when numba is installed; the numpy path otherwise
    from sim_harness.sim import raycast_kernels as _kernels
except ImportError:  # pragma: no cover
    _kernels = None  # type: ignore[assignment]

FloatArray = NDArray[np.float64]

# TinyRenderer's lighting as pybullet sets it up (TinyRendererVisualShapeConverter, up axis z).
_LIGHT_DIR_WORLD = np.array([-50.0, 30.0, 100.0]) / math.sqrt(50.0**2 + 30.0**2 + 100.0**2)
_AMBIENT, _DIFFUSE, _SPECULAR, _SPECULAR_POWER = 0.6, 0.35, 0.05, 2.0
_GRAY_WEIGHTS = np.array([0.299, 0.587, 0.114])  # ITU-R BT.601, as PyBulletRenderer
# Where TinyRenderer samples a pixel, from its top-left corner (x right, y down): the bottom-left
# corner. The default, so that both renderers draw the drones on the same pixels.
TINYRENDERER_SAMPLE_PX = (0.0, 1.0)


def pixel_rays_camera(sample_offset_px: tuple[float, float]) -> FloatArray:
    """Unit ray per pixel in camera coordinates (right, up, forward): (64, 64, 3).

    `sample_offset_px` = (dx, dy): where in the pixel the ray passes, from its top-left corner.
    """
    half = math.tan(math.radians(FOV_DEG) / 2)
    dx, dy = sample_offset_px
    idx = np.arange(FACE_SIZE_PX)
    x = ((idx + dx) / FACE_SIZE_PX * 2.0 - 1.0) * half
    y = (1.0 - (idx + dy) / FACE_SIZE_PX * 2.0) * half
    rays = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((1, 1))), axis=-1)
    unit: FloatArray = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    return unit


def _enumerate(start: NDArray[np.intp], count: NDArray[np.intp]) -> tuple[NDArray[np.intp], ...]:
    """For runs [start, start + count): the run of each element and the element's value."""
    run = np.repeat(np.arange(len(count)), count)
    first = np.cumsum(count) - count
    return run, start[run] + np.arange(int(count.sum())) - first[run]


def _sphere_pixels(
    centre: FloatArray, box: NDArray[np.intp], radius_m: float, offset: tuple[float, float]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pixels whose ray meets a sphere, per sphere: (sphere index, flat pixel index), each (M,).

    `centre` (T, 3) in camera coordinates (right, up, forward); `box` (4, T): first and last
    column, first and last row that can see it. Per row, the columns whose ray meets the sphere
    form one interval: (w.c)^2 >= (|c|^2 - r^2) |w|^2 for w = (u, v, 1), a quadratic in u.
    Spheres that reach behind the eye keep their whole box.
    """
    size = FACE_SIZE_PX
    half = math.tan(math.radians(FOV_DEG) / 2)
    c0, c1, r0, r1 = box
    t, row = _enumerate(r0, r1 - r0 + 1)
    cx, cy, cz = centre[t, 0], centre[t, 1], centre[t, 2]
    v = (1.0 - (row + offset[1]) / size * 2.0) * half
    k = cx * cx + cy * cy + cz * cz - radius_m * radius_m
    e = v * cy + cz
    a = cx * cx - k
    disc = (cx * e) ** 2 - a * (e * e - k * (v * v + 1.0))
    bounded = (a < 0.0) & (k > 0.0)  # else the sphere's image is unbounded: test every pixel
    root = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        u_lo, u_hi, u_mid = (-cx * e + root) / a, (-cx * e - root) / a, -cx * e / a
    # Within the interval w.c keeps one sign; a negative one is the cone behind the eye.
    empty = bounded & ((disc < 0.0) | (cx * u_mid + e <= 0.0))
    lo = np.where(bounded, np.ceil((u_lo / half + 1.0) * size / 2 - offset[0]), c0[t])
    hi = np.where(bounded, np.floor((u_hi / half + 1.0) * size / 2 - offset[0]), c1[t])
    lo = np.maximum(np.nan_to_num(lo, nan=size), c0[t]).astype(np.intp)
    hi = np.minimum(np.nan_to_num(hi, nan=-1), c1[t]).astype(np.intp)
    run, col = _enumerate(lo, np.where(empty, 0, np.maximum(hi - lo + 1, 0)))
    which, pix = t[run], row[run] * size + col
    check = ~bounded[run]
    if check.any():
        rays = pixel_rays_camera(offset).reshape(-1, 3)[pix[check]]
        c = centre[which[check]]
        b = np.einsum("mi,mi->m", rays, c)
        c2 = np.einsum("mi,mi->m", c, c) - radius_m * radius_m
        keep = np.ones(len(pix), dtype=bool)
        keep[check] = ((b * b >= c2) & (b > 0.0)) | (c2 < 0.0)
        which, pix = which[keep], pix[keep]
    return which, pix


def _face_bases() -> FloatArray:
    """Columns right, up, axis of each face in the body frame: (6, 3, 3)."""
    return np.array(
        [np.column_stack([f.right_body_flu, f.up_body_flu, f.axis_body_flu]) for f in FACES]
    )


class RaycastRenderer:
    """All agents' six 64x64 faces in one vectorized pass (numpy, CPU), grayscale."""

    name = "raycast"

    def __init__(
        self,
        near_m: float = 0.05,
        far_m: float = 120.0,
        scene: SceneSpec | None = None,
        sample_offset_px: tuple[float, float] = TINYRENDERER_SAMPLE_PX,
        compiled: bool | None = None,
        supersample: int = 1,
    ) -> None:
        """`compiled`: use the numba kernels (None: when numba is installed). `supersample` K > 1:
        drones sampled on a K x K grid in each pixel and averaged (`sample_offset_px` unused)."""
        require_int_range("supersample", supersample, 1, 16)
        self.near_m = near_m
        self.far_m = far_m
        self.environment = Environment(scene or SceneSpec())
        self.supersample = supersample
        if supersample > 1:
            self.name = "raycast-aa"
            grid = [(i + 0.5) / supersample for i in range(supersample)]
            offsets = [(dx, dy) for dy in grid for dx in grid]
        else:
            offsets = [sample_offset_px]
        self._samples = [(o, pixel_rays_camera(o).reshape(-1, 3)) for o in offsets]
        self.sample_offset_px = sample_offset_px
        self._bases = _face_bases()
        self._solid: tuple[QuadGeometry, DroneSolid] | None = None
        self._buf: tuple[NDArray[Any], ...] | None = None
        if compiled and _kernels is None:
            raise ImportError("RaycastRenderer(compiled=True) needs numba: pip install numba")
        self.compiled = _kernels is not None if compiled is None else compiled

    def _buffers(self, n_px: int) -> tuple[NDArray[Any], ...]:
        """Per-pixel depth (inf), owner (-1), part, plane and touched list, reused across calls."""
        if self._buf is None or len(self._buf[0]) < n_px:
            self._buf = (
                np.full(n_px, np.inf),
                *(np.full(n_px, -1, dtype=np.intp) for _ in range(4)),
            )
        return self._buf

    def solid(self, geometry: QuadGeometry) -> DroneSolid:
        if self._solid is None or self._solid[0] != geometry:
            self._solid = (geometry, drone_solid(geometry))
        return self._solid[1]

    def render(
        self,
        world: World,
        pos_world_enu: ArrayLike,
        q_world_body: ArrayLike,
        agents: Sequence[int] | None = None,
    ) -> NDArray[np.uint8]:
        """(K, 64, 384) uint8 strips of the requested agents (all when `agents` is None)."""
        pos = np.asarray(pos_world_enu, dtype=np.float64)
        rot = quat_to_rotmat(np.asarray(q_world_body, dtype=np.float64))
        chosen = np.arange(len(pos)) if agents is None else np.asarray(agents, dtype=np.intp)
        eyes, _, _ = camera_poses(pos, np.asarray(q_world_body, dtype=np.float64))
        if self.compiled:
            out = _kernels.environment(self.environment, eyes[chosen], rot[chosen])
        else:
            out = self.environment.shade(eyes[chosen], rot[chosen])
        flat = out.reshape(-1)
        solid = self.solid(world.geometry)
        if self.supersample == 1:
            pixel, gray = self.drone_pixels(pos, rot, chosen, solid)
            flat[pixel] = gray
        else:
            change = np.zeros_like(flat)  # summed over the samples: drone gray - environment
            for sample in self._samples:
                pixel, gray = self.drone_pixels(pos, rot, chosen, solid, sample)
                change[pixel] += gray - flat[pixel]  # one nearest drone per pixel and sample
            flat += change / len(self._samples)
        return stitch(np.clip(np.rint(out), 0, 255).astype(np.uint8))

    def drone_pixels(
        self,
        pos: FloatArray,
        rot: FloatArray,
        chosen: NDArray[np.intp],
        solid: DroneSolid,
        sample: tuple[tuple[float, float], FloatArray] | None = None,
    ) -> tuple[NDArray[np.intp], FloatArray]:
        """Flat indices into (K, 6, 64, 64) of pixels where a drone is nearest, and their grays.

        `sample`: (offset in the pixel, its rays (64 * 64, 3)); default the renderer's first."""
        offset, rays_cam = sample or self._samples[0]
        n = len(pos)
        size = FACE_SIZE_PX
        # Camera frames in the world: (K, 6, 3, 3), columns right, up, axis; eyes (K, 6, 3).
        basis = np.einsum("kij,fjc->kfic", rot[chosen], self._bases)
        eye = pos[chosen, None, :] + np.einsum(
            "kij,fj->kfi", rot[chosen], np.array([f.position_body_flu for f in FACES])
        )
        rel = pos[None, None, :, :] - eye[:, :, None, :]  # (K, 6, N, 3)
        cam = np.einsum("kfic,kfni->kfnc", basis, rel)  # (K, 6, N, 3): right, up, forward
        x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
        r = solid.radius_m
        keep = (z > self.near_m - r) & (z < self.far_m + r)
        keep &= chosen[:, None, None] != np.arange(n)[None, None, :]
        half = math.tan(math.radians(FOV_DEG) / 2)
        # Extremes of x/z (and y/z) over the sphere: tangent planes through the eye.
        box = np.empty((4, *x.shape))
        safe = z > r * 1.001
        zz = np.where(safe, z * z - r * r, 1.0)
        for i, c in enumerate((x, y)):
            root = np.sqrt(np.maximum(c * c + zz, 0.0)) * r
            box[2 * i] = np.where(safe, (c * z - root) / zz, -np.inf)
            box[2 * i + 1] = np.where(safe, (c * z + root) / zz, np.inf)
        dx, dy = offset
        col0 = np.ceil((box[0] / half + 1.0) * size / 2 - dx)
        col1 = np.floor((box[1] / half + 1.0) * size / 2 - dx)
        row0 = np.ceil((1.0 - box[3] / half) * size / 2 - dy)
        row1 = np.floor((1.0 - box[2] / half) * size / 2 - dy)
        col0, row0 = np.clip(col0, 0, size).astype(np.intp), np.clip(row0, 0, size).astype(np.intp)
        col1 = np.clip(col1, -1, size - 1).astype(np.intp)
        row1 = np.clip(row1, -1, size - 1).astype(np.intp)
        keep &= (col1 >= col0) & (row1 >= row0)
        kk, ff, jj = np.nonzero(keep)
        if len(kk) == 0:
            return np.zeros(0, dtype=np.intp), np.zeros(0)
        centre = cam[kk, ff, jj]  # (T, 3)
        boxes = np.stack([col0[kk, ff, jj], col1[kk, ff, jj], row0[kk, ff, jj], row1[kk, ff, jj]])
        # The ray in the observed drone's body frame: R_j^T B_kf ray_cam, from R_j^T (eye - p_j).
        rot_j = rot[jj]  # (T, 3, 3)
        cam_to_body = np.einsum("tij,tic->tjc", rot_j, basis[kk, ff])  # (T, 3, 3)
        origin = np.einsum("tij,ti->tj", rot_j, -rel[kk, ff, jj])  # (T, 3)
        if self.compiled:
            depth, owner, part, plane, touched = self._buffers(len(chosen) * len(FACES) * size**2)
            n_hit = _kernels.cast_drones(
                centre, boxes, cam_to_body, origin, (kk * len(FACES) + ff) * size * size,
                rays_cam, size, half, r, *offset, self.near_m, self.far_m,
                solid.normal, solid.offset, np.any(solid.normal != 0.0, axis=2).sum(axis=1),
                solid.part_centre, solid.part_radius_m, depth, owner, part, plane, touched,
            )  # fmt: skip
            flat = touched[:n_hit].copy()
            hit_t, t = depth[flat], owner[flat]
            depth[flat], owner[flat] = np.inf, -1  # the buffers are clean for the next call
            d = np.einsum("mjc,mc->mj", cam_to_body[t], rays_cam[flat % (size * size)])
            hit_body = origin[t] + hit_t[:, None] * d
            return flat, self._shade(hit_body, part[flat], plane[flat], rot[jj[t]], solid)
        which, pix = _sphere_pixels(centre, boxes, r, offset)
        ray = rays_cam[pix]
        o = origin[which]
        d = (cam_to_body[which] * ray[:, None, :]).sum(axis=2)
        t_hit, part, plane = self._intersect(o, d, solid)
        cos_axis = rays_cam[pix, 2]
        depth = t_hit * cos_axis
        hit = np.isfinite(t_hit) & (depth >= self.near_m) & (depth <= self.far_m)
        which, pix, d, o = which[hit], pix[hit], d[hit], o[hit]
        t_hit, part, plane = t_hit[hit], part[hit], plane[hit]
        flat = (kk[which] * len(FACES) + ff[which]) * size * size + pix
        # Nearest drone per pixel: sort by depth far to near, keep the last write of each pixel.
        order = np.lexsort((-t_hit, flat))
        flat, t_hit = flat[order], t_hit[order]
        last = np.ones(len(flat), dtype=bool)
        last[:-1] = flat[1:] != flat[:-1]
        sel = order[last]
        gray = self._shade(
            o[sel] + t_hit[last, None] * d[sel], part[sel], plane[sel], rot[jj[which[sel]]], solid
        )
        return flat[last], gray

    @staticmethod
    def _intersect(
        o: FloatArray, d: FloatArray, solid: DroneSolid
    ) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.intp]]:
        """Nearest entry along each ray (M,) into any part (inf if none), the part, its plane.

        Only (ray, part) pairs whose ray passes the part's bounding sphere are slab-tested.
        """
        n_rays, n_parts = len(d), len(solid.offset)
        oc = o[:, None, :] - solid.part_centre[None, :, :]  # (M, P, 3)
        b = np.einsum("mpi,mi->mp", oc, d)
        c = np.einsum("mpi,mpi->mp", oc, oc) - solid.part_radius_m**2
        passes = (b * b >= c) & ((b < 0.0) | (c < 0.0))  # (M, P)
        rays, parts, enters, planes = [], [], [], []
        for p in range(n_parts):
            ray = np.nonzero(passes[:, p])[0]
            used = np.any(solid.normal[p] != 0.0, axis=1)  # the padding planes constrain nothing
            normal, offset = solid.normal[p, used], solid.offset[p, used]
            denom = d[ray] @ normal.T  # (Q, planes)
            num = offset - o[ray] @ normal.T
            with np.errstate(divide="ignore", invalid="ignore"):
                t = num / denom
            t_in = np.where(denom < 0.0, t, -np.inf)
            plane = np.argmax(t_in, axis=1)
            enter = t_in[np.arange(len(ray)), plane]
            leave = np.where(denom > 0.0, t, np.inf).min(axis=1, initial=np.inf)
            outside_parallel = ((denom == 0.0) & (num < 0.0)).any(axis=1)
            ok = (enter <= leave) & (enter > 0.0) & ~outside_parallel
            rays.append(ray[ok])
            parts.append(np.full(int(ok.sum()), p))
            enters.append(enter[ok])
            planes.append(np.nonzero(used)[0][plane[ok]])
        ray, part = np.concatenate(rays), np.concatenate(parts)
        enter, plane = np.concatenate(enters), np.concatenate(planes)
        best = np.full(n_rays, np.inf)
        np.minimum.at(best, ray, enter)
        nearest = enter == best[ray]
        part_of = np.zeros(n_rays, dtype=np.intp)
        plane_of = np.zeros(n_rays, dtype=np.intp)
        part_of[ray[nearest]] = part[nearest]
        plane_of[ray[nearest]] = plane[nearest]
        return best, part_of, plane_of

    @staticmethod
    def _shade(
        hit_body: FloatArray,
        part: NDArray[np.intp],
        plane: NDArray[np.intp],
        rot_world_body: FloatArray,
        solid: DroneSolid,
    ) -> FloatArray:
        """TinyRenderer's fragment colour, as gray, of hits at `hit_body` (M, 3) body frame."""
        normal = solid.normal[part, plane]
        smooth = solid.smooth[part, plane]
        if smooth.any():
            idx = np.nonzero(smooth)[0]
            sp, sq = part[idx], plane[idx]
            pa, edge = solid.rim_pa[sp, sq], solid.rim_pb[sp, sq] - solid.rim_pa[sp, sq]
            s = np.einsum("mi,mi->m", hit_body[idx] - pa, edge) / np.einsum("mi,mi->m", edge, edge)
            s = np.clip(s, 0.0, 1.0)[:, None]
            blend = (1.0 - s) * solid.rim_a[sp, sq] + s * solid.rim_b[sp, sq]
            normal = normal.copy()
            normal[idx] = blend / np.linalg.norm(blend, axis=1, keepdims=True)
        n_world = np.einsum("mij,mj->mi", rot_world_body, normal)
        lam = n_world @ _LIGHT_DIR_WORLD
        reflect = 2.0 * lam[:, None] * n_world - _LIGHT_DIR_WORLD
        reflect /= np.linalg.norm(reflect, axis=1, keepdims=True)
        spec = np.maximum(reflect[:, 2], 0.0) ** _SPECULAR_POWER
        gain = _AMBIENT + _DIFFUSE * np.maximum(lam, 0.0) + _SPECULAR * spec
        rgb = np.minimum(np.floor(solid.rgb_u8[part] * gain[:, None]), 255.0)
        gray: FloatArray = rgb @ _GRAY_WEIGHTS
        return gray
