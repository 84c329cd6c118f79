"""`swarm-sim dataset generate | inspect | merge | aggregate`."""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from sim_harness.dataset.aggregate import (
    DEFAULT_EXPERIMENTS,
    AggregateConfig,
    aggregate,
    default_rules,
)
from sim_harness.dataset.generate import generate, merge
from sim_harness.dataset.inspect import inspect_dataset
from sim_harness.dataset.spec import PRESETS, DatasetSpec
from sim_harness.dataset.store import open_dataset
from sim_harness.errors import ConfigError
from sim_harness.suites import DEFAULT_MODEL_PATH


def _shard(text: str) -> tuple[int, int]:
    try:
        index, count = (int(x) for x in text.split("/"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected INDEX/COUNT such as 0/4, got {text!r}") from exc
    return index, count


def add_dataset_commands(sub: Any) -> None:
    """Register `dataset` and its subcommands on the top-level subparsers."""
    p = sub.add_parser("dataset", help="generate, inspect and merge camera datasets")
    dsub = p.add_subparsers(dest="dataset_command", required=True)
    g = dsub.add_parser(
        "generate",
        help="generate (or resume) a dataset",
        description="Generate the paper's dataset. Interrupted? Run the same command again: it "
        "resumes where it stopped. The same seed gives the same dataset with any --workers.",
    )
    g.add_argument("--preset", default="quick", choices=sorted(PRESETS), help="default quick")
    g.add_argument("--out", type=Path, default=None, help="folder (default data/<preset>-s<seed>)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    for split in ("train", "val", "test"):
        g.add_argument(f"--{split}", type=int, default=None, help=f"{split} samples (min)")
    g.add_argument("--agents", type=int, default=None, help="drones per run (default 9)")
    g.add_argument("--max-run-s", type=float, default=None, help="time limit of a run")
    g.add_argument("--shard", type=_shard, default=(0, 1), help="INDEX/COUNT (default 0/1)")
    g.add_argument("--no-progress", action="store_true")
    g.set_defaults(handler=_generate)
    i = dsub.add_parser("inspect", help="counts, splits, terminations, target stats, figures")
    i.add_argument("dataset", type=Path)
    i.add_argument(
        "--out", type=Path, default=None, help="figures folder (default DATASET/inspect)"
    )
    i.set_defaults(handler=_inspect)
    m = dsub.add_parser("merge", help="unite shards made with the same parameters")
    m.add_argument("sources", type=Path, nargs="+")
    m.add_argument("--out", type=Path, required=True)
    m.set_defaults(handler=_merge)
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
    a.add_argument("--workers", type=int, default=1)
    a.add_argument("--no-progress", action="store_true")
    a.set_defaults(handler=_aggregate)


def command_line() -> str:
    """This process's `swarm-sim` command line, quoted, for manifests and checkpoints."""
    return shlex.join(["swarm-sim", *sys.argv[1:]])


def _generate(args: argparse.Namespace) -> int:
    overrides: dict[str, Any] = {"seed": args.seed}
    for split in ("train", "val", "test"):
        if getattr(args, split) is not None:
            overrides[f"{split}_samples"] = getattr(args, split)
    if args.agents is not None:
        overrides["n_agents"] = args.agents
    if args.max_run_s is not None:
        overrides["max_run_s"] = args.max_run_s
    overrides["shard_index"], overrides["shard_count"] = args.shard
    spec = DatasetSpec.preset(args.preset, **overrides)
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    out = args.out or Path("data") / f"{args.preset}-s{args.seed}"
    try:
        dataset = generate(
            out, spec, workers=args.workers, progress=not args.no_progress, command=command_line()
        )
    except KeyboardInterrupt:
        print(
            f"swarm-sim: interrupted; completed runs are kept in {out}: run the same command "
            "to resume",
            file=sys.stderr,
        )
        return 130
    counts = dataset.manifest["counts"]
    gen = dataset.manifest["generation"]
    print(
        f"wrote {out}: train {counts['train']}, val {counts['val']}, test {counts['test']} "
        f"samples in {gen['wall_s']:.0f} s with {gen['workers']} worker(s)"
    )
    return 0


def _inspect(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.dataset)
    report = inspect_dataset(dataset, args.out or args.dataset / "inspect")
    print(report["text"])
    print(f"\nwrote {report['histogram']} and {report['samples']}")
    return 0


def _aggregate(args: argparse.Namespace) -> int:
    config = AggregateConfig(
        model_path=args.model or DEFAULT_MODEL_PATH,
        runs=args.runs,
        experiments=tuple(e.strip() for e in args.experiments.split(",") if e.strip()),
        seed_base=args.seed_base,
        workers=args.workers,
        rules=default_rules(args.dispersion_m, args.max_run_s),
    )
    started = time.perf_counter()
    try:
        dataset = aggregate(args.out, config, not args.no_progress, command_line())
    except KeyboardInterrupt:
        print(f"swarm-sim: interrupted; finished runs are kept in {args.out}", file=sys.stderr)
        return 130
    counts = dataset.manifest["counts"]
    print(
        f"wrote {args.out}: train {counts['train']}, val {counts['val']}, test {counts['test']} "
        f"samples in {time.perf_counter() - started:.0f} s"
    )
    return 0


def _merge(args: argparse.Namespace) -> int:
    dataset = merge(args.sources, args.out, command=command_line())
    counts = dataset.manifest["counts"]
    print(f"wrote {args.out}: train {counts['train']}, val {counts['val']}, test {counts['test']}")
    return 0
