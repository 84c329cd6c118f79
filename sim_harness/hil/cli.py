"""`swarm-sim hil`: the unmodified onboard daemon, one per drone, flying the pybullet swarm.

    swarm-sim hil --agents 9 --scenario common --seed 1000 --duration 60 --compare
    swarm-sim hil --agents 3 --faults sim_harness/hil/plans/unplug_and_kill.toml

Each drone: six pty cameras rendered from the shared world, a PX4 emulator (MAVLink over
loopback UDP) flying that drone's vehicle, and `companion run --config FILE` as systemd starts
it. Results in --out: report.md, hil.json, summary.json, figures, and per drone its config,
daemon output and MCAP flight log.
"""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path
from typing import Any

from companion.errors import ConfigError
from companion.flocking import FlockingParams
from sim_harness.experiments.suites import SHIPPED_LOW_PASS_HZ
from sim_harness.hil.plans import PLANS_DIR
from sim_harness.learning.shipped import SHIPPED_MODEL_PATH
from sim_harness.sim.renderers import (
    DEFAULT_RENDERER,
    add_renderer_option,
    make_renderer,
    renderer_of_model,
)
from sim_harness.sim.scenarios import SCENARIOS, ScenarioConfig, build_scenario


def add_hil_commands(sub: Any) -> None:
    """Register `hil` on the top-level subparsers."""
    p = sub.add_parser(
        "hil",
        help="fly N unmodified `companion run` daemons in the simulated swarm (real time)",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--agents", type=int, default=3, help="number of drones (default 3)")
    p.add_argument("--scenario", default="common", choices=SCENARIOS, help="default common")
    p.add_argument("--seed", type=int, default=1000, help="spawn seed (default 1000)")
    p.add_argument("--duration", type=float, default=30.0, help="flight seconds (default 30)")
    p.add_argument("--vmax", type=float, default=2.0, help="speed cap in m/s (default 2)")
    p.add_argument("--model", type=Path, default=SHIPPED_MODEL_PATH, help="policy file")
    p.add_argument("--out", type=Path, default=None, help="default runs/hil-<scenario>-n<N>-s<S>")
    p.add_argument(
        "--autopilot",
        default="emulator",
        choices=("emulator", "px4-sitl"),
        help="what flies each drone: our PX4 emulator on the shared pybullet vehicle (default), "
        "or real PX4 SITL with its own quadrotor model (SIH), one per drone, in a loopback-only "
        "network namespace (needs root and PX4_SITL_TARBALL)",
    )
    p.add_argument("--faults", type=Path, default=None, help=f"fault plan TOML (see {PLANS_DIR})")
    p.add_argument(
        "--compare",
        action="store_true",
        help="also fly the in-process CNN controller on the same seed and model",
    )
    p.add_argument(
        "--daemon-set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a key of every drone's companion.toml (TOML value), e.g. "
        "daemon.tick_on_frames=false; repeatable",
    )
    add_renderer_option(p, follows_model=True)
    p.set_defaults(handler=_hil)


def daemon_overrides(items: list[str]) -> dict[str, dict[str, Any]]:
    """`SECTION.KEY=VALUE` items (VALUE in TOML syntax) as {section: {key: value}}."""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        key, sep, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not section or not name:
            raise ConfigError(f"daemon-set: {item!r} is not SECTION.KEY=VALUE")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()  # a bare word is a string
        out.setdefault(section, {})[name] = value
    return out


def _hil(args: argparse.Namespace) -> int:
    from sim_harness.hil.faults import load_plan

    if not 1 <= args.agents <= 30:
        raise ConfigError(f"agents: {args.agents} is outside [1, 30]")
    if not 1.0 <= args.duration <= 600.0:
        raise ConfigError(f"duration: {args.duration} is outside [1, 600] s")
    if not args.model.is_file():
        raise ConfigError(f"model: no policy file at {args.model.resolve()}")
    config = ScenarioConfig(
        name=args.scenario,
        n_agents=args.agents,
        seed=args.seed,
        flocking=FlockingParams(v_max_mps=args.vmax),
        duration_s=args.duration,
    )
    if args.autopilot == "px4-sitl":
        from sim_harness.hil.px4_sitl import MAX_INSTANCES, unavailable_reason

        if args.faults is not None:
            raise ConfigError("faults: fault plans need --autopilot emulator")
        if args.agents > MAX_INSTANCES:
            raise ConfigError(f"agents: at most {MAX_INSTANCES} with --autopilot px4-sitl")
        reason = unavailable_reason()
        if reason is not None:
            raise ConfigError(f"autopilot px4-sitl: {reason}")
    plan = load_plan(args.faults, args.agents) if args.faults is not None else None
    duration = args.duration if plan is None else max(args.duration, plan.end_s)
    out = args.out or Path("runs") / f"hil-{args.scenario}-n{args.agents}-s{args.seed}"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"out: cannot create {out}: {exc.strerror}") from exc
    overrides = daemon_overrides(args.daemon_set)
    doc = fly_hil(
        config,
        args.model,
        out,
        duration,
        plan,
        args.compare,
        overrides,
        args.autopilot,
        args.renderer,
    )
    s = doc["summary"]
    print(
        f"{'VALID' if doc['valid'] else 'INVALID'}: arrived {s['arrived']}, "
        f"d_min {_number(s['d_min_m'])} m, order {_number(s['order_mean'])}; "
        f"report {out / 'report.md'}"
    )
    if "faults" in doc:
        for outcome in doc["faults"]["outcomes"]:
            print(f"{'PASS' if outcome['passed'] else 'FAIL'} {outcome['event']}")
    return 0 if doc["valid"] else 1


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def fly_hil(
    config: ScenarioConfig,
    model: Path,
    out: Path,
    duration_s: float,
    plan: Any = None,
    compare: bool = False,
    overrides: dict[str, dict[str, Any]] | None = None,
    autopilot: str = "emulator",
    renderer: str | None = None,
) -> dict[str, Any]:
    """Fly the HIL swarm (and the in-process CNN if `compare`), write `out`, return hil.json.

    `autopilot`: "emulator" (our PX4 emulator per drone on the shared pybullet vehicle) or
    "px4-sitl" (real PX4 SITL per drone, `sim_harness.hil.px4_swarm`). `renderer`: what draws
    the camera images; None: the one the model was trained on."""
    from sim_harness.hil.results import write_results
    from sim_harness.hil.swarm import HilConfig, HilSwarm

    scenario = build_scenario(config)
    renderer = renderer or renderer_of_model(model)

    def say(message: str) -> None:
        print(f"hil: {message}", flush=True)

    hil = HilConfig(daemon_overrides=overrides or {}, renderer=renderer)
    if autopilot == "px4-sitl":
        from sim_harness.hil.px4_results import write_px4_results
        from sim_harness.hil.px4_swarm import Px4Swarm

        swarm = Px4Swarm(scenario, model, out, hil, progress=say)
        px4_run = swarm.run(duration_s)
        ref = fly_in_process(config, model, duration_s, renderer) if compare else None
        return write_px4_results(swarm, px4_run, out, ref)
    run = HilSwarm(scenario, model, out, hil, faults=plan, progress=say).run(duration_s)
    reference = None
    if compare:
        say("flying the in-process CNN on the same seed")
        reference = fly_in_process(config, model, duration_s, renderer)
    return write_results(run, out, reference)


def fly_in_process(
    config: ScenarioConfig, model: Path, duration_s: float, renderer: str = DEFAULT_RENDERER
) -> Any:
    """The same scenario flown by the in-process CNN controller (shipped low-pass), with the
    same renderer as the HIL cameras."""
    import dataclasses

    from sim_harness.experiments.vision_controller import (
        VisionControlConfig,
        VisionController,
        load_policy,
    )
    from sim_harness.sim.rollout import fly
    from sim_harness.sim.world import SimRates

    rates = SimRates()
    policy = load_policy(model)
    try:
        law = VisionControlConfig.from_flocking(config.flocking, SHIPPED_LOW_PASS_HZ)
        controller = VisionController(policy, law, rates.control_dt_s)
        scenario = build_scenario(dataclasses.replace(config, duration_s=duration_s))
        return fly(scenario, controller, rates, renderer=make_renderer(renderer))
    finally:
        policy.close()
