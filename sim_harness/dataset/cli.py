"""`swarm-sim dataset generate | inspect | merge | rerender | close-range` (`aggregate` flies the
CNN: experiments/cli)."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Any

from sim_harness.dataset.generate import generate, merge
from sim_harness.dataset.inspect import inspect_dataset
from sim_harness.dataset.spec import COMPRESSIONS, PRESETS, DatasetSpec
from sim_harness.dataset.store import open_dataset
from sim_harness.errors import ConfigError
from sim_harness.sim.executor import add_cluster_options, cluster_choice
from sim_harness.sim.out_dir import require_writable_dir
from sim_harness.sim.renderers import RENDERERS, add_renderer_option


def _shard(text: str) -> tuple[int, int]:
    try:
        index, count = (int(x) for x in text.split("/"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected INDEX/COUNT such as 0/4, got {text!r}") from exc
    return index, count


def add_dataset_commands(sub: Any) -> Any:
    """Register `dataset` and its subcommands; return its subparsers (`aggregate` joins later)."""
    p = sub.add_parser("dataset", help="generate, inspect, merge and redraw camera datasets")
    dsub = p.add_subparsers(dest="dataset_command", required=True)
    g = dsub.add_parser(
        "generate",
        help="generate (or resume) a dataset",
        description="Generate the paper's dataset. Interrupted? Run the same command again: it "
        "resumes where it stopped. The same seed gives the same dataset with any --workers "
        "and on a Ray cluster (--ray).",
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
    add_renderer_option(g)
    g.add_argument(
        "--compression",
        choices=COMPRESSIONS,
        default="deflate",
        help="run files: deflate (default: half the disk, ~0.45 ms of a core per sample) or none "
        "(stored: twice the disk, the fastest generation)",
    )
    add_cluster_options(g)
    g.set_defaults(handler=_generate)
    i = dsub.add_parser("inspect", help="counts, splits, terminations, target stats, figures")
    i.add_argument("dataset", type=Path)
    i.add_argument(
        "--out",
        type=Path,
        default=None,
        help="figures folder (default runs/inspect/<dataset name>; never the dataset itself)",
    )
    i.set_defaults(handler=_inspect)
    m = dsub.add_parser("merge", help="unite shards made with the same parameters")
    m.add_argument("sources", type=Path, nargs="+")
    m.add_argument("--out", type=Path, required=True)
    m.set_defaults(handler=_merge)
    r = dsub.add_parser(
        "rerender",
        help="draw a dataset's images again with another renderer (same states and labels)",
        description="Redraw every image of a complete dataset from the poses it recorded, with "
        "another renderer, into a new folder: no flight is repeated (aggregated datasets "
        "included). Interrupted? Run the same command again.",
    )
    r.add_argument("source", type=Path, help="a complete dataset")
    r.add_argument("--out", type=Path, required=True, help="the new dataset's folder")
    r.add_argument("--renderer", required=True, choices=RENDERERS)
    r.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    r.add_argument(
        "--vary-scene",
        type=int,
        default=None,
        metavar="SEED",
        help="draw each run against its own random ground and sky (from this seed) instead of "
        "the default scene",
    )
    r.add_argument("--no-progress", action="store_true")
    r.set_defaults(handler=_rerender)
    c = dsub.add_parser(
        "close-range",
        help="close encounters from a dataset's flocks: one pair brought within 0.4-1.1 m per step",
        description="For some steps of every run of a complete dataset, move one drone's nearest "
        "neighbour along their line to a distance drawn in [--min, --max] m, draw the whole flock "
        "again and label every drone with the teacher's command of the new positions: the close "
        "range that flights almost never reach, with exact labels. Interrupted? Run the same "
        "command again.",
    )
    c.add_argument("source", type=Path, help="a complete dataset (default scene)")
    c.add_argument("--out", type=Path, required=True, help="the new dataset's folder")
    c.add_argument("--steps-per-run", type=int, default=30, help="steps drawn a run (default 30)")
    c.add_argument("--min", dest="min_m", type=float, default=0.4, help="metres (default 0.4)")
    c.add_argument("--max", dest="max_m", type=float, default=1.1, help="metres (default 1.1)")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument(
        "--bearing",
        default="kept",
        choices=("kept", "corner"),
        help="kept (default): the neighbour comes closer along its recorded line; corner: it is "
        "put towards a corner of the near drone's cube map, where it is split across three faces",
    )
    c.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    c.add_argument("--no-progress", action="store_true")
    c.set_defaults(handler=_close_range)
    return dsub


def command_line() -> str:
    """This process's `swarm-sim` command line, quoted, for manifests and checkpoints."""
    return shlex.join(["swarm-sim", *sys.argv[1:]])


def _generate(args: argparse.Namespace) -> int:
    overrides: dict[str, Any] = {
        "seed": args.seed,
        "renderer": args.renderer,
        "compression": args.compression,
    }
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
    cluster = cluster_choice(args)
    out = args.out or Path("data") / f"{args.preset}-s{args.seed}"
    require_writable_dir(out)
    try:
        dataset = generate(
            out,
            spec,
            workers=args.workers,
            progress=not args.no_progress,
            command=command_line(),
            cluster=cluster,
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
    out = args.out or Path("runs") / "inspect" / args.dataset.resolve().name
    report = inspect_dataset(dataset, require_writable_dir(out))
    print(report["text"])
    print(f"\nwrote {report['histogram']} and {report['samples']}")
    return 0


def _rerender(args: argparse.Namespace) -> int:
    from sim_harness.dataset.rerender import rerender

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    require_writable_dir(args.out)
    dataset = rerender(
        args.source,
        args.out,
        args.renderer,
        workers=args.workers,
        progress=not args.no_progress,
        command=command_line(),
        vary_scene=args.vary_scene,
    )
    counts = dataset.manifest["counts"]
    print(
        f"wrote {args.out} ({args.renderer}): train {counts['train']}, val {counts['val']}, "
        f"test {counts['test']} samples"
    )
    return 0


def _close_range(args: argparse.Namespace) -> int:
    from sim_harness.dataset.close_range import CloseRangeDraw, close_range

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    draw = CloseRangeDraw(args.steps_per_run, args.min_m, args.max_m, args.seed, args.bearing)
    require_writable_dir(args.out)
    dataset = close_range(
        args.source,
        args.out,
        draw,
        workers=args.workers,
        progress=not args.no_progress,
        command=command_line(),
    )
    counts = dataset.manifest["counts"]
    print(
        f"wrote {args.out}: train {counts['train']}, val {counts['val']}, "
        f"test {counts['test']} samples"
    )
    return 0


def _merge(args: argparse.Namespace) -> int:
    require_writable_dir(args.out)
    dataset = merge(args.sources, args.out, command=command_line())
    counts = dataset.manifest["counts"]
    print(f"wrote {args.out}: train {counts['train']}, val {counts['val']}, test {counts['test']}")
    return 0
