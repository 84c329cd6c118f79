"""`swarm-sim demo` and `swarm-sim experiments`: teacher and CNN side by side, with a report.

swarm-sim demo                                   # 9 drones, common + opposing goals, 1 seed
swarm-sim experiments --suite paper --seeds 5 --model models/swarm_cnn.pt --out runs/paper
swarm-sim experiments --suite generalization --workers 2
swarm-sim experiments --suite bar --ray auto      # on the Ray cluster this machine joined
swarm-sim experiments --suite bar                 # every experiment, 20 evaluation seeds: the bar
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.errors import ModelError
from sim_harness.dataset.cli import command_line
from sim_harness.experiments.aggregate import (
    DEFAULT_EXPERIMENTS,
    AggregateConfig,
    aggregate,
    default_rules,
)
from sim_harness.experiments.suites import (
    DEFAULT_SEEDS,
    EVAL_SEED_BASE,
    EXPERIMENTS,
    LABELS,
    SHIPPED_LOW_PASS_HZ,
    SHIPPED_MODEL_PATH,
    SUITES,
    SuiteConfig,
)
from sim_harness.sim.executor import add_cluster_options, cluster_choice
from sim_harness.sim.out_dir import require_writable_dir
from sim_harness.sim.renderers import add_renderer_option, renderer_of_model
from sim_harness.sim.world import SimRates

if TYPE_CHECKING:
    from sim_harness.experiments.runner import RunRecord

log = logging.getLogger(__name__)

DEMO_SEEDS = 1
# How long the demo takes (4 flights; the two CNN flights render 9 x 6 views per step and take
# most of it): measured 75 s on 2 idle cores, 94 s on a busy machine. The README says the same.
DEMO_DURATION = "about 5 min on 2 cores"
HOW_TO_GET_A_MODEL = (
    "make one with `swarm-sim dataset generate --preset quick`, "
    "`swarm-sim train --dataset data/quick-s0`, then `swarm-sim export --checkpoint "
    f"runs/train/quick-s0 --dataset data/quick-s0` (writes {SHIPPED_MODEL_PATH}); "
    "or pass --model PATH"
)


def require_model(path: Path) -> Path:
    """Return `path` if the policy file exists; else raise `ModelError` naming where it looked."""
    if not path.is_file():
        looked = path if path.is_absolute() else f"{path} (that is, {path.absolute()})"
        raise ModelError(f"no model at {looked}: {HOW_TO_GET_A_MODEL}")
    return path


def _add_common_options(p: argparse.ArgumentParser, default_out: Path, seeds_help: str) -> None:
    p.add_argument(
        "--model",
        type=Path,
        default=SHIPPED_MODEL_PATH,
        help=f"exported policy file (default {SHIPPED_MODEL_PATH})",
    )
    p.add_argument("--seeds", type=int, default=None, help=seeds_help)
    p.add_argument(
        "--seed-base",
        type=int,
        default=EVAL_SEED_BASE,
        help=f"first scenario seed (default {EVAL_SEED_BASE}; evaluation seeds are >= 1000)",
    )
    p.add_argument("--out", type=Path, default=default_out, help=f"folder (default {default_out})")
    p.add_argument("--workers", type=int, default=None, help="flights in parallel (default 1)")
    p.add_argument(
        "--low-pass",
        type=_cutoff,
        default=SHIPPED_LOW_PASS_HZ,
        metavar="HZ",
        help="low-pass the CNN output with this cut-off, or 'off' "
        f"(default {_cutoff_text(SHIPPED_LOW_PASS_HZ)}, what the shipped model is flown with)",
    )
    p.add_argument(
        "--duration", type=float, default=None, help="cut every flight at this many seconds"
    )
    p.add_argument("--no-gradcam", action="store_true", help="skip the Grad-CAM strip")
    add_renderer_option(p, follows_model=True)
    p.add_argument("--quiet", action="store_true", help="no line per flight")
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress during each flight (a bar on a terminal, else a line every 10 %%)",
    )


def _cutoff_text(cutoff_hz: float | None) -> str:
    return "off" if cutoff_hz is None else f"{cutoff_hz:g} Hz"


def _cutoff(text: str) -> float | None:
    """`--low-pass`: a cut-off in Hz, or `off`."""
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a cut-off in Hz or 'off', got {text!r}"
        ) from None


def add_experiment_commands(sub: Any) -> None:
    """Register `demo` and `experiments` on the top-level subparsers."""
    demo = sub.add_parser(
        "demo",
        help="9 drones, common and opposing goals, flown by the shipped CNN and by the teacher "
        f"({DEMO_DURATION})",
        description="The main job: flies the 9-drone common-goal and opposing-goals experiments "
        "with the shipped model and with the position-based teacher (same seeds) and writes the "
        f"report, showing each flight's progress. Takes {DEMO_DURATION}.",
    )
    _add_common_options(demo, Path("runs/demo"), f"seeds per experiment (default {DEMO_SEEDS})")
    demo.set_defaults(handler=_demo)
    exp = sub.add_parser(
        "experiments",
        help="an experiment suite, teacher and CNN over several seeds, with its report",
    )
    exp.add_argument(
        "--suite",
        default="paper",
        choices=sorted(SUITES),
        help="paper (common, opposing), generalization (N 3 / 12, a faster flock, no goal), bar "
        "(all six, the acceptance bar)",
    )
    seeds_help = "seeds per experiment (default: " + ", ".join(
        f"{k} {v}" for k, v in DEFAULT_SEEDS.items()
    )
    _add_common_options(exp, Path("runs/experiments"), seeds_help + ")")
    exp.add_argument(
        "--experiments",
        type=lambda text: tuple(k for k in text.split(",") if k),
        default=None,
        metavar="KEY,...",
        help="fly only these of the suite's experiments (" + ", ".join(EXPERIMENTS) + ")",
    )
    exp.add_argument(
        "--output-jitter",
        type=float,
        default=0.0,
        metavar="MPS",
        help="sensitivity check: add seeded uniform noise in [-MPS, MPS] to every CNN output "
        "component (e.g. 1e-6, the size of float rounding; default 0)",
    )
    exp.add_argument(
        "--ground",
        type=int,
        default=None,
        metavar="SEED",
        help="robustness check: draw the CNN's images against unseen ground and sky number SEED "
        "(default: the scene the datasets are drawn in)",
    )
    add_cluster_options(exp, shared_dir=False)
    exp.set_defaults(handler=_experiments)


def _describe(record: RunRecord) -> str:
    s = record.summary
    end = f"arrived after {s['arrival_time_s']:.1f} s" if s["arrived"] else "time limit"
    d_min = "n/a" if s["d_min_m"] is None else f"{s['d_min_m']:.2f} m"
    d_max = "n/a" if s["d_max_m"] is None else f"{s['d_max_m']:.2f} m"
    return (
        f"{record.experiment} / {LABELS[record.controller]} / seed {record.seed}: {end}, "
        f"d_min {d_min}, d_max {d_max}, contacts {s['physical_contacts']} "
        f"({record.log.wall_time_s:.0f} s wall)"
    )


def _run(
    args: argparse.Namespace, suite: str, default_seeds: int | None, demo: bool = False
) -> int:
    require_model(args.model)
    cluster = cluster_choice(args) if hasattr(args, "ray") else None
    config = SuiteConfig(
        suite=suite,
        model_path=args.model,
        n_seeds=args.seeds if args.seeds is not None else default_seeds,
        seed_base=args.seed_base,
        low_pass_cutoff_hz=args.low_pass,
        workers=1 if args.workers is None else args.workers,
        rates=SimRates(),
        duration_s=args.duration,
        renderer=args.renderer or renderer_of_model(args.model),
        experiments=getattr(args, "experiments", None),
        output_jitter_mps=getattr(args, "output_jitter", 0.0),
        ground_seed=getattr(args, "ground", None),
    )
    require_writable_dir(args.out)
    n_flights = 2 * len(config.experiment_list) * len(config.seeds)
    print(
        f"{suite}: {n_flights} flights (teacher and CNN, seeds {config.seeds[0]}..; "
        f"{config.renderer} images)",
        flush=True,
    )

    def progress(record: RunRecord, done: int, total: int) -> None:
        if not args.quiet:
            print(f"[{done}/{total}] {_describe(record)}", flush=True)

    # torch and matplotlib load here, not when the CLI starts.
    from sim_harness.experiments.bar import bar_checks
    from sim_harness.experiments.report import bar_scope, write_report
    from sim_harness.experiments.runner import run_suite, save_runs

    result = run_suite(config, on_run=progress, progress=not args.no_progress, cluster=cluster)
    save_runs(result, args.out)
    report = write_report(result, args.out, gradcam=not args.no_gradcam, demo=demo)
    scope = bar_scope(config, demo)
    for check in bar_checks(result):
        verdict = "pass" if check.passed else "FAIL"
        print(f"bar ({scope}): {verdict}: {check.name} ({check.detail})")
    print(f"report: {report} (flights in {args.out / 'runs'})")
    return 0


def _demo(args: argparse.Namespace) -> int:
    return _run(args, "paper", DEMO_SEEDS, demo=True)


def _experiments(args: argparse.Namespace) -> int:
    return _run(args, args.suite, None)


def add_aggregate_command(dsub: Any) -> None:
    """Register `dataset aggregate` (a DAgger round flies the CNN) on the dataset subparsers."""
    a = dsub.add_parser(
        "aggregate",
        help="label the states an exported CNN flies into (DAgger round)",
        description="Fly the CNN through the experiment scenarios on training seeds (0..999) and "
        "label every state it visits with the teacher's command: a dataset to add to training "
        "with `swarm-sim train --extra-train DIR`. Interrupted? Run the same command again.",
    )
    a.add_argument("--model", type=Path, default=None, help="policy file (default: shipped)")
    a.add_argument("--out", type=Path, required=True, help="dataset folder")
    a.add_argument("--runs", type=int, default=60, help="flights (default 60)")
    a.add_argument(
        "--experiments",
        default=",".join(DEFAULT_EXPERIMENTS),
        help="comma-separated, flown in turn (default %(default)s)",
    )
    a.add_argument("--seed-base", type=int, default=0, help="first scenario seed (< 1000)")
    a.add_argument(
        "--dispersion-m",
        type=float,
        default=7.0,
        help="stop a flight once a pair is this far apart (default 7, the paper's; < r_max)",
    )
    a.add_argument(
        "--max-run-s", type=float, default=15.0, help="stop a flight after this long (default 15)"
    )
    a.add_argument(
        "--after-arrival-s",
        type=float,
        default=None,
        metavar="S",
        help="fly on through the flock's arrival (each goal group's centroid within 2 m) for S "
        "more seconds instead of stopping when an agent comes within 1 m of its point (the "
        "dataset's rule, default): the bunching of a flock converging on its point is labelled",
    )
    a.add_argument("--workers", type=int, default=None, help="flights in parallel (default 1)")
    a.add_argument("--no-progress", action="store_true")
    add_renderer_option(a, follows_model=True)
    add_cluster_options(a)
    a.set_defaults(handler=_aggregate)


def _aggregate(args: argparse.Namespace) -> int:
    cluster = cluster_choice(args)
    model = require_model(args.model or SHIPPED_MODEL_PATH)
    config = AggregateConfig(
        model_path=model,
        runs=args.runs,
        experiments=tuple(e.strip() for e in args.experiments.split(",") if e.strip()),
        seed_base=args.seed_base,
        workers=1 if args.workers is None else args.workers,
        after_arrival_s=args.after_arrival_s,
        rules=dataclasses.replace(
            default_rules(args.dispersion_m, args.max_run_s),
            renderer=args.renderer or renderer_of_model(model),
        ),
    )
    require_writable_dir(args.out)
    started = time.perf_counter()
    try:
        dataset = aggregate(args.out, config, not args.no_progress, command_line(), cluster)
    except KeyboardInterrupt:
        print(f"swarm-sim: interrupted; finished runs are kept in {args.out}", file=sys.stderr)
        return 130
    counts = dataset.manifest["counts"]
    print(
        f"wrote {args.out}: train {counts['train']}, val {counts['val']}, test {counts['test']} "
        f"samples in {time.perf_counter() - started:.0f} s"
    )
    return 0
