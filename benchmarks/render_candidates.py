"""How the batched renderer was chosen: three ways to find the drone pixels, timed on one scene.

    python benchmarks/render_candidates.py [--agents 9 30] [--repeats 5]
        [--warp-path DIR]   # where `pip install --target DIR warp-lang` put NVIDIA Warp

All agents' six faces of the paper's common-goal spawn (N agents, random small tilts), drone
pixels only (the environment, shared by all, is timed separately):

- `numpy_slabs`: `sim_harness.sim.raycast`'s numpy path (sphere culling to per-row pixel intervals,
  per-part spheres, slab test against nine convex parts).
- `numpy_triangles`: the same culling, then Moller-Trumbore against the 220 mesh triangles.
- `numba_slabs`: the slab path as compiled loops (`sim_harness.sim.raycast_kernels`), as shipped
  when numba is installed.
- `warp_bvh`: NVIDIA Warp on the CPU: one `wp.Mesh` (BVH) of all drones in world coordinates,
  one `mesh_query_ray` per pixel of every face (no culling: that is what a BVH is for); kernel
  compilation and mesh building are excluded. Skipped when Warp cannot be imported.

CPU seconds (process time) per control step, median of repeats. Writes JSON (default
benchmarks/results/render_candidates.json).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from companion.camera.layout import FACE_SIZE_PX, FACES
from companion.frames import quat_from_euler_zyx, quat_to_rotmat
from sim_harness.experiments.machine import machine
from sim_harness.sim.drone_solid import DroneSolid
from sim_harness.sim.quad_body import QuadGeometry, quad_mesh
from sim_harness.sim.raycast import TINYRENDERER_SAMPLE_PX, RaycastRenderer, pixel_rays_camera
from sim_harness.sim.render import camera_poses
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

RESULTS = Path(__file__).resolve().parent / "results"


def scene(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pos = build_scenario(ScenarioConfig(n_agents=n, seed=seed)).initial_pos_world_enu
    q = np.stack(
        [quat_from_euler_zyx(*rng.uniform(-0.2, 0.2, 2), rng.uniform(-3, 3)) for _ in range(n)]
    )
    return pos, q


def triangles_intersect(
    geometry: QuadGeometry,
) -> Callable[[np.ndarray, np.ndarray, DroneSolid], tuple[np.ndarray, ...]]:
    mesh = quad_mesh(geometry)
    v = np.asarray(mesh.vertices)[np.asarray(mesh.indices).reshape(-1, 3)]  # (T, 3, 3)
    v0, e1, e2 = v[:, 0], v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]

    def intersect(o: np.ndarray, d: np.ndarray, solid: DroneSolid) -> tuple[np.ndarray, ...]:
        p = np.cross(d[:, None, :], e2[None])  # (M, T, 3)
        det = np.einsum("mti,ti->mt", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o[:, None, :] - v0[None]
            u = np.einsum("mti,mti->mt", s, p) * inv
            qv = np.cross(s, e1[None])
            w = np.einsum("mi,mti->mt", d, qv) * inv
            t = np.einsum("mti,ti->mt", qv, e2) * inv
        ok = (det < -1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)  # front faces
        t = np.where(ok, t, np.inf)
        tri = np.argmin(t, axis=1)
        zeros = np.zeros(len(d), dtype=np.intp)
        return t[np.arange(len(d)), tri], zeros, zeros

    return intersect


def time_drone_pixels(renderer: RaycastRenderer, pos: np.ndarray, q: np.ndarray, repeats: int):
    rot = quat_to_rotmat(q)
    chosen = np.arange(len(pos))
    solid = renderer.solid(QuadGeometry())
    renderer.drone_pixels(pos, rot, chosen, solid)
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        renderer.drone_pixels(pos, rot, chosen, solid)
        times.append(time.process_time() - t0)
    return statistics.median(times)


def time_warp(pos: np.ndarray, q: np.ndarray, repeats: int) -> dict[str, Any]:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    mesh = quad_mesh(QuadGeometry())
    verts_body = np.asarray(mesh.vertices)
    idx = np.asarray(mesh.indices)
    rot = quat_to_rotmat(q)
    world = np.einsum("nij,vj->nvi", rot, verts_body) + pos[:, None, :]
    indices = (idx[None, :] + len(verts_body) * np.arange(len(pos))[:, None]).reshape(-1)
    t0 = time.process_time()
    wmesh = wp.Mesh(
        points=wp.array(world.reshape(-1, 3), dtype=wp.vec3, device="cpu"),
        indices=wp.array(indices.astype(np.int32), dtype=int, device="cpu"),
    )
    build_s = time.process_time() - t0

    @wp.kernel
    def cast(
        mesh_id: wp.uint64,
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        depth: wp.array(dtype=float),
    ) -> None:
        i = wp.tid()
        q_ = wp.mesh_query_ray(mesh_id, origins[i], dirs[i], 200.0)
        if q_.result:
            depth[i] = q_.t
        else:
            depth[i] = -1.0

    eyes, _, _ = camera_poses(pos, q)
    rays = pixel_rays_camera(TINYRENDERER_SAMPLE_PX).reshape(-1, 3)
    bases = np.array(
        [np.column_stack([f.right_body_flu, f.up_body_flu, f.axis_body_flu]) for f in FACES]
    )
    dirs = np.einsum("nij,fjc,pc->nfpi", rot, bases, rays).reshape(-1, 3)
    origins = np.repeat(eyes.reshape(-1, 3), FACE_SIZE_PX * FACE_SIZE_PX, axis=0)
    o = wp.array(origins.astype(np.float32), dtype=wp.vec3, device="cpu")
    d = wp.array(dirs.astype(np.float32), dtype=wp.vec3, device="cpu")
    out = wp.zeros(len(dirs), dtype=float, device="cpu")
    t0 = time.process_time()
    wp.launch(cast, dim=len(dirs), inputs=[wmesh.id, o, d, out], device="cpu")
    wp.synchronize()
    compile_s = time.process_time() - t0
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        wmesh.refit()
        wp.launch(cast, dim=len(dirs), inputs=[wmesh.id, o, d, out], device="cpu")
        wp.synchronize()
        times.append(time.process_time() - t0)
    return {
        "version": wp.__version__,
        "rays": len(dirs),
        "first_launch_s (compile)": compile_s,
        "mesh_build_s": build_s,
        "cpu_s_per_step": statistics.median(times),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--agents", type=int, nargs="+", default=[9, 30])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warp-path", default=None)
    ap.add_argument("--out", type=Path, default=RESULTS / "render_candidates.json")
    args = ap.parse_args()
    if args.warp_path:
        sys.path.insert(0, args.warp_path)
    rows: dict[str, Any] = {}
    for n in args.agents:
        pos, q = scene(n)
        slabs = RaycastRenderer(compiled=False)
        tris = RaycastRenderer(compiled=False)
        tris._intersect = triangles_intersect(QuadGeometry())  # type: ignore[method-assign]
        row: dict[str, Any] = {
            "numpy_slabs_cpu_s": time_drone_pixels(slabs, pos, q, args.repeats),
            "numpy_triangles_cpu_s": time_drone_pixels(tris, pos, q, args.repeats),
        }
        try:
            row["numba_slabs_cpu_s"] = time_drone_pixels(
                RaycastRenderer(compiled=True), pos, q, args.repeats
            )
        except ImportError as exc:
            row["numba_slabs_cpu_s"] = f"not importable: {exc}"
        eyes, _, _ = camera_poses(pos, q)
        t0 = time.process_time()
        for _ in range(args.repeats):
            slabs.environment.shade(eyes, quat_to_rotmat(q))
        row["environment_cpu_s"] = (time.process_time() - t0) / args.repeats
        try:
            row["warp_bvh"] = time_warp(pos, q, args.repeats)
        except ImportError as exc:
            row["warp_bvh"] = f"not importable: {exc}"
        rows[str(n)] = row
        print(n, json.dumps(row, indent=1), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine(), "agents": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
