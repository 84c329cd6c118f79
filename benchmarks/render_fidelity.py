"""How closely the ray-cast renderer reproduces pybullet's images, over random views.

    python benchmarks/render_fidelity.py [--views 300] [--seed 0]

Each view: a scenario (common, opposing, self-propelled; N = 3-12) spawned from a random seed,
random attitudes (roll and pitch up to +-0.5 rad, any yaw), one observer, and one other drone moved
to a random direction at a distance drawn log-uniformly from 0.6 to 20 m. The observer's strip is
rendered by `PyBulletRenderer` and by `RaycastRenderer` (at its default sample position,
TinyRenderer's, and at the pixel centre), and compared:

- `mad`: per-pixel mean absolute difference of the 64x384 strips (gray levels);
- `iou`: intersection over union of the drone silhouettes (pixels that differ from the same
  renderer's image without that drone; views where neither shows it are left out), per view and
  pooled (all views' intersections over all views' unions);
- `drone_px`: drone-visible pixel counts of each renderer.

Prints a summary and writes JSON (default benchmarks/results/render_fidelity.json): summary per
sample position, per distance bin, and every view.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np

from companion.frames import quat_from_euler_zyx
from sim_harness.sim.raycast import TINYRENDERER_SAMPLE_PX, RaycastRenderer
from sim_harness.sim.render import PyBulletRenderer
from sim_harness.sim.scenarios import SCENARIOS, ScenarioConfig, build_scenario
from sim_harness.sim.world import World

RESULTS = Path(__file__).resolve().parent / "results"
FAR = np.array([5000.0, 5000.0, 5.0])
DIST_BINS_M = (0.6, 1.5, 4.0, 10.0, 20.0)


def random_view(rng: np.random.Generator) -> dict[str, Any]:
    name = str(rng.choice(SCENARIOS))
    n = int(rng.integers(3, 13))
    seed = int(rng.integers(0, 10_000))
    pos = build_scenario(ScenarioConfig(name=name, n_agents=n, seed=seed)).initial_pos_world_enu
    pos = pos.copy()
    q = np.stack(
        [quat_from_euler_zyx(*rng.uniform(-0.5, 0.5, 2), rng.uniform(-np.pi, np.pi)) for _ in pos]
    )
    observer, other = (int(i) for i in rng.choice(n, size=2, replace=False))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    distance = float(np.exp(rng.uniform(np.log(0.6), np.log(20.0))))
    pos[other] = pos[observer] + distance * direction
    return {"scenario": name, "n": n, "seed": seed, "observer": observer, "other": other,
            "distance_m": distance, "pos": pos, "q": q}  # fmt: skip


def compare(
    a: np.ndarray, empty_a: np.ndarray, b: np.ndarray, empty_b: np.ndarray
) -> dict[str, float]:
    ma, mb = a != empty_a, b != empty_b
    union = int((ma | mb).sum())
    return {
        "inter": int((ma & mb).sum()),
        "union": union,
        "mad": float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean()),
        "iou": float((ma & mb).sum() / union) if union else float("nan"),
        "drone_px_pybullet": int(ma.sum()),
        "drone_px_raycast": int(mb.sum()),
    }


def summarize(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
    def stats(sel: list[dict[str, Any]]) -> dict[str, Any]:
        iou = np.array([r[key]["iou"] for r in sel])
        iou = iou[np.isfinite(iou)]
        mad = np.array([r[key]["mad"] for r in sel])
        pa = np.array([r[key]["drone_px_pybullet"] for r in sel])
        pr = np.array([r[key]["drone_px_raycast"] for r in sel])
        return {
            "views": len(sel),
            "views_with_a_drone": len(iou),
            "mad_mean": float(mad.mean()),
            "mad_max": float(mad.max()),
            "iou_mean": float(iou.mean()) if len(iou) else None,
            "iou_pooled": sum(r[key]["inter"] for r in sel)
            / max(sum(r[key]["union"] for r in sel), 1),
            "iou_p05": float(np.percentile(iou, 5)) if len(iou) else None,
            "iou_min": float(iou.min()) if len(iou) else None,
            "drone_px_pybullet_mean": float(pa.mean()),
            "drone_px_raycast_mean": float(pr.mean()),
            "drone_px_abs_diff_max": int(np.abs(pa - pr).max()),
        }

    out = {"all": stats(rows)}
    for lo, hi in itertools.pairwise(DIST_BINS_M):
        sel = [r for r in rows if lo <= r["distance_m"] < hi]
        if sel:
            out[f"{lo}-{hi} m"] = stats(sel)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS / "render_fidelity.json")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    pybullet = PyBulletRenderer()
    raycast = {
        "tinyrenderer_sample": RaycastRenderer(),
        "pixel_centre_sample": RaycastRenderer(sample_offset_px=(0.5, 0.5)),
    }
    rows: list[dict[str, Any]] = []
    worlds: dict[int, World] = {}
    try:
        for _ in range(args.views):
            view = random_view(rng)
            world = worlds.get(view["n"]) or worlds.setdefault(view["n"], World(view["n"]))
            pos, q, obs = view.pop("pos"), view.pop("q"), [view["observer"]]
            a = pybullet.render(world, pos, q, obs)[0]
            gone = pos.copy()
            gone[view["other"]] = FAR  # the environment and the rest of the flock
            empty = pybullet.render(world, gone, q, obs)[0]
            for key, renderer in raycast.items():
                b = renderer.render(world, pos, q, obs)[0]
                view[key] = compare(a, empty, b, renderer.render(world, gone, q, obs)[0])
            rows.append(view)
    finally:
        for w in worlds.values():
            w.close()
    summary = {key: summarize(rows, key) for key in raycast}
    for key, s in summary.items():
        print(key, json.dumps(s["all"]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "views": args.views,
        "seed": args.seed,
        "default_sample_px": list(TINYRENDERER_SAMPLE_PX),
        "summary": summary,
        "rows": rows,
    }
    args.out.write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
