"""`swarm-sim average | ensemble`: one policy from several, written like `export`.

    swarm-sim average --models models/A.pt runs/train/B --weights 0.5 0.5 --dataset data/quick-s0 \
        --out models/AB.pt                     # one network from the mean of fine-tunes' weights
    swarm-sim ensemble --models models/A.pt models/C.pt --dataset data/quick-s0 --out models/AC.pt
                                               # one policy calling both, their answers averaged
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from companion.errors import ConfigError
from sim_harness.dataset.cli import command_line
from sim_harness.learning.symmetry_views import GROUPS
from sim_harness.sim.out_dir import require_writable_dir


def add_combining_commands(sub: Any) -> None:
    """Register `average` and `ensemble` on the top-level subparsers."""
    a = sub.add_parser(
        "average",
        help="one network from the weighted mean of several networks' weights (fine-tunes of "
        "one ancestor), evaluated on the test split and written as a policy",
    )
    _add_sources(a, "policy files or checkpoints (>= 2)")
    a.add_argument(
        "--symmetry",
        choices=tuple(GROUPS),
        default="none",
        help="average the result over the rig's symmetric views, as `export --symmetry`",
    )
    a.set_defaults(handler=_average)

    n = sub.add_parser(
        "ensemble",
        help="one policy file that calls several policies and averages their answers (networks "
        "that err differently: noise averaged out, at every member's inference cost), evaluated "
        "on the test split",
    )
    _add_sources(n, "exported policy files (2-8), each flown with its own symmetry average")
    n.set_defaults(handler=_ensemble)


def _add_sources(parser: argparse.ArgumentParser, models_help: str) -> None:
    """`--models`, `--weights`, `--dataset`, `--out`, `--eval-out`: what `average` and
    `ensemble` combine and where the result goes."""
    parser.add_argument("--models", type=Path, nargs="+", required=True, help=models_help)
    parser.add_argument(
        "--weights",
        type=float,
        nargs="+",
        default=None,
        help="each model's share, in (0, 1], summing to 1 (default equal)",
    )
    parser.add_argument(
        "--dataset", type=Path, required=True, help="the dataset they were trained on"
    )
    parser.add_argument("--out", type=Path, required=True, help="policy file (.pt)")
    parser.add_argument("--eval-out", type=Path, default=None, help="default runs/eval/<out>-test")


def _combined_outputs(args: argparse.Namespace) -> tuple[Path, Any]:
    """`average`'s and `ensemble`'s checks before anything is read: the output's suffix and
    folders; then the dataset. Returns (eval-out, dataset)."""
    from sim_harness.dataset.store import open_dataset

    if args.out.suffix != ".pt":
        raise ConfigError(f"out: the policy file must end in .pt, got {args.out}")
    eval_out = args.eval_out or Path("runs/eval") / f"{args.out.stem}-test"
    require_writable_dir(args.out.parent)
    require_writable_dir(eval_out, "eval-out")
    return eval_out, open_dataset(args.dataset)


def _require_dataset(path: Path, dataset_id: str | None, dataset: Any, where: Path) -> None:
    if dataset_id is not None and dataset_id != dataset.id:
        raise ConfigError(
            f"models: {path} was trained on dataset {dataset_id}, but {where} is {dataset.id}"
        )


def _average(args: argparse.Namespace) -> int:
    from sim_harness.learning.average import average_policies, averaged_chain, require_weights

    require_weights(args.weights, len(args.models))  # before anything is read
    eval_out, dataset = _combined_outputs(args)
    model, sources = average_policies(args.models, args.weights)
    for source in sources:
        _require_dataset(source.path, source.dataset_id, dataset, args.dataset)
    shares = ", ".join(f"{s.weight:g} x {s.path}" for s in sources)
    print(f"averaged the weights of {shares}")
    training = {
        "command": command_line(),
        "output_gain": 1.0,
        **averaged_chain(sources, command_line()),
    }
    from sim_harness.learning.cli import _evaluate_and_write

    _evaluate_and_write(model, dataset, training, args.out, eval_out, args.symmetry)
    return 0


def _ensemble(args: argparse.Namespace) -> int:
    import torch

    from sim_harness.learning.cli import _describe_metrics
    from sim_harness.learning.ensemble import (
        export_ensemble,
        load_members,
        require_shares,
        scripted_ensemble,
    )
    from sim_harness.learning.evaluate import evaluate_split

    require_shares(args.weights, len(args.models))  # before anything is read
    eval_out, dataset = _combined_outputs(args)
    members = load_members(args.models, args.weights)
    for member in members:
        recorded = member.loaded.metadata.get("dataset") or {}
        _require_dataset(member.path, recorded.get("id"), dataset, args.dataset)
    print("ensemble of " + ", ".join(f"{m.weight:g} x {m.path} ({m.symmetry})" for m in members))
    scripted = scripted_ensemble(members)
    test = dataset.split("test")
    report = evaluate_split(scripted, test, eval_out, title=f"{args.out.name} on test")
    result = export_ensemble(
        members,
        args.out,
        {"split": "test", **report},
        command_line(),
        scripted=scripted,
        check_images_u8=torch.from_numpy(test.images[: min(16, test.n_samples)].copy()),
    )
    print(f"test {_describe_metrics(report['metrics'])}")
    print(
        f"wrote {result.path} (sha256 {result.sha256[:16]}..., graph vs eager members "
        f"{result.max_abs_diff_mps:.1e} m/s), {result.path.with_suffix('.json').name}, "
        f"{result.weights_path.name}; evaluation in {eval_out}/"
    )
    return 0
