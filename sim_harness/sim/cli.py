"""`swarm-sim fly | view`: one teacher flight with its figures, or what one drone sees."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from companion.errors import ConfigError
from companion.flocking import FlockingParams
from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.out_dir import require_writable_dir
from sim_harness.sim.plots import save_flight_figures
from sim_harness.sim.renderers import add_renderer_option, make_renderer
from sim_harness.sim.rollout import FlightLog, fly, save_flight, summarize
from sim_harness.sim.scenarios import SCENARIOS, ScenarioConfig, build_scenario
from sim_harness.sim.world import SimRates


def _add_flight_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--agents", type=int, default=9, help="number of drones (default 9)")
    p.add_argument("--seed", type=int, default=0, help="spawn seed (default 0)")
    p.add_argument("--vmax", type=float, default=2.0, help="speed cap in m/s (default 2)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="time limit in s (default: 90 common, 60 opposing, 30 self-propelled)",
    )
    p.add_argument(
        "--goal-distance",
        type=float,
        default=30.0,
        help="migration point distance from the spawn centre in m (default 30)",
    )
    p.add_argument("--physics-hz", type=int, default=100, help="physics rate (default 100)")
    p.add_argument("--control-hz", type=int, default=10, help="control rate (default 10)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def add_sim_commands(sub: Any) -> None:
    """Register `fly` and `view` on the top-level subparsers."""
    p_fly = sub.add_parser("fly", help="fly one scenario with the position-based teacher")
    p_fly.add_argument(
        "--scenario", default="common", help=f"one of: {', '.join(SCENARIOS)} (default common)"
    )
    p_fly.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default runs/<scenario>-n<agents>-s<seed>)",
    )
    _add_flight_options(p_fly)
    p_fly.set_defaults(handler=_fly)
    p_view = sub.add_parser("view", help="write one drone's 64x384 camera image at a step")
    p_view.add_argument("--scenario", default="common", help=f"one of: {', '.join(SCENARIOS)}")
    p_view.add_argument("--step", type=int, default=0, help="control step (teacher flight)")
    p_view.add_argument("--agent", type=int, default=0, help="which drone's view")
    p_view.add_argument("--out", type=Path, default=Path("runs/view"), help="output folder")
    _add_flight_options(p_view)
    add_renderer_option(p_view)
    p_view.set_defaults(handler=_view)


def _rates(args: argparse.Namespace) -> SimRates:
    return SimRates(physics_hz=args.physics_hz, control_hz=args.control_hz)


def _fly(args: argparse.Namespace) -> int:
    config = _config(args, args.scenario)
    rates = _rates(args)
    out = args.out or Path("runs") / f"{config.name}-n{config.n_agents}-s{config.seed}"
    require_writable_dir(out)
    log = _fly_one(config, rates, out, not args.no_progress)
    print(_describe(summarize(log)))
    print(
        f"wrote {out}/ (flight.png, trajectories.png, distances.png, order.png, "
        f"summary.json, steps.npz)"
    )
    return 0


def _config(args: argparse.Namespace, scenario: str) -> ScenarioConfig:
    return ScenarioConfig(
        name=scenario,
        n_agents=args.agents,
        seed=args.seed,
        flocking=FlockingParams(v_max_mps=args.vmax),
        goal_distance_m=args.goal_distance,
        duration_s=args.duration,
    )


def _fly_one(config: ScenarioConfig, rates: SimRates, out: Path, progress: bool) -> FlightLog:
    scenario = build_scenario(config)
    log = fly(scenario, TeacherController(config.flocking), rates, progress=progress)
    save_flight(log, out)
    save_flight_figures(log, out)
    return log


def _describe(summary: dict[str, Any]) -> str:
    arrival = (
        f"arrived after {summary['arrival_time_s']:.1f} s"
        if summary["arrived"]
        else f"stopped at the {summary['duration_s']:.0f} s time limit"
    )

    def metres(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.2f} m"

    def number(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.2f}"

    return (
        f"{summary['scenario']:>14} | {arrival} | d_min {metres(summary['d_min_m'])}, "
        f"d_max {metres(summary['d_max_m'])}, order {number(summary['order_mean'])}, "
        f"contacts {summary['physical_contacts']}"
    )


def _view(args: argparse.Namespace) -> int:
    rates = _rates(args)
    from sim_harness.sim.view import save_layout, save_strip
    from sim_harness.sim.world import World

    config = _config(args, args.scenario)
    if not 0 <= args.agent < config.n_agents:
        raise ConfigError(
            f"agent: {args.agent} is outside the allowed range [0, {config.n_agents - 1}]"
        )
    if args.step < 0:
        raise ConfigError(f"step: {args.step} must be >= 0")
    config = dataclasses.replace(config, duration_s=max(args.step, 1) / rates.control_hz)
    scenario = build_scenario(config)
    require_writable_dir(args.out)
    log = fly(scenario, TeacherController(config.flocking), rates, progress=False)
    last = log.n_steps - 1
    if args.step > last:
        why = "the flock arrived" if log.stop_reason == "arrived" else "the flight ended"
        raise ConfigError(
            f"step: {args.step} is past the end of the flight: {why} at step {last} "
            f"(t = {last / rates.control_hz:.1f} s); the last step available is {last}"
        )
    step = args.step
    with World(config.n_agents) as world:
        image = make_renderer(args.renderer).render(
            world, log.pos_world_enu[step], log.q_world_body[step], [args.agent]
        )[0]
    stem = f"{config.name}-s{config.seed}-step{step}-agent{args.agent}"
    strip = save_strip(image, args.out / f"{stem}-strip.png")
    layout = save_layout(
        image,
        args.out / f"{stem}-faces.png",
        f"{config.name}, seed {config.seed}, step {step} "
        f"(t = {step / rates.control_hz:.1f} s), drone {args.agent}",
    )
    print(f"wrote {strip} (64x384, enlarged) and {layout}")
    return 0
