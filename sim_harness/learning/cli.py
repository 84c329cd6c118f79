"""`swarm-sim train | evaluate | export | average | ensemble | gradcam`: the learning pipeline
from the command line.

    swarm-sim train --dataset data/quick-s0 --out runs/train/quick-s0      # --resume to continue
    swarm-sim export --checkpoint runs/train/quick-s0 --dataset data/quick-s0 --out models/M.pt
    swarm-sim average --models models/A.pt runs/train/B --weights 0.5 0.5 --dataset data/quick-s0 \
        --out models/AB.pt                     # one network from the mean of fine-tunes' weights
    swarm-sim ensemble --models models/A.pt models/C.pt --dataset data/quick-s0 --out models/AC.pt
                                               # one policy calling both, their answers averaged
    swarm-sim evaluate --model models/M.pt --dataset data/quick-s0 --split test --out DIR
    swarm-sim gradcam --model models/M.pt --dataset data/quick-s0 --samples 0,5,9 --out DIR

`--model` takes a policy file (`.pt`, verified against its hash) or a training checkpoint (a run
directory or a `.ckpt`); it defaults to the shipped model.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from companion.errors import ConfigError
from sim_harness.dataset.cli import command_line
from sim_harness.learning.cli_combine import add_combining_commands
from sim_harness.learning.lr_schedule import LR_SCHEDULES
from sim_harness.learning.shipped import SHIPPED_MODEL_PATH
from sim_harness.learning.symmetry_views import GROUPS
from sim_harness.sim.out_dir import require_writable_dir

SPLITS = ("train", "val", "test")


def _samples(text: str) -> list[int]:
    try:
        samples = [int(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected indices such as 0,5,9, got {text!r}") from exc
    if not samples or min(samples) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative indices, got {text!r}")
    return samples


def add_learning_commands(sub: Any) -> None:
    """Register `train`, `evaluate`, `export`, `average`, `ensemble` and `gradcam` on the
    top-level subparsers."""
    t = sub.add_parser(
        "train",
        help="train the CNN on a dataset (paper hyper-parameters)",
        description="Train the DroNet-style CNN with the paper's recipe. Interrupted? Run the same "
        "command with --resume: it continues from the last completed epoch.",
    )
    t.add_argument("--dataset", type=Path, required=True, help="generated dataset folder")
    t.add_argument("--out", type=Path, default=None, help="run folder (default runs/train/<data>)")
    t.add_argument("--max-epochs", type=int, default=200, help="(default 200; early stop first)")
    t.add_argument("--batch-size", type=int, default=128)
    t.add_argument("--lr", type=float, default=5e-3)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument(
        "--dropout",
        type=float,
        default=0.5,
        help="dropout probability before the linear head (default 0.5, the paper's; lower "
        "shrinks the rare large commands less: models/README.md)",
    )
    t.add_argument(
        "--arch",
        default="dronet",
        help="the network: dronet (the strip as one image, default) or cube (each cube-map face "
        "padded with its neighbours; same weights, so --init-from either works)",
    )
    t.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    t.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    t.add_argument("--limit-train", type=int, default=None, help="train on N samples (quick runs)")
    t.add_argument("--limit-val", type=int, default=None, help="validate on N samples")
    t.add_argument("--resume", action="store_true", help="continue from OUT/last.ckpt")
    t.add_argument(
        "--extra-train",
        type=Path,
        action="append",
        default=[],
        metavar="DIR",
        help="add this aggregated dataset's training split (repeatable; loads the splits in RAM); "
        "a folder given k times is shown k times per epoch",
    )
    t.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="PATH",
        help="fine-tune: start from these weights (checkpoint or policy file)",
    )
    t.add_argument(
        "--augment",
        choices=tuple(GROUPS),
        default="none",
        help="show each sample in a random view of this symmetry group of the camera rig "
        "(quarter turns c4, mirror, both d4), its label transformed to match (default none)",
    )
    t.add_argument(
        "--weight-speed",
        type=float,
        default=None,
        metavar="MPS",
        help="weight each sample's squared error by max(1, |target| / MPS), at most "
        "--weight-cap, so rare large commands are not shrunk (default: plain MSE, the paper's)",
    )
    t.add_argument(
        "--weight-near",
        type=float,
        default=None,
        metavar="M",
        help="weight each sample's squared error by (M / nearest neighbour's distance)^4 inside "
        "M, at most --weight-cap, so the rare close-range states are fitted; with --weight-speed "
        "a sample takes the larger weight (default: off)",
    )
    t.add_argument("--weight-cap", type=float, default=4.0, help="largest weight (default 4)")
    t.add_argument(
        "--weight-shortfall",
        type=float,
        default=None,
        metavar="K",
        help="add K x the squared shortfall of the answer along the teacher's command on samples "
        "with a neighbour closer than --shortfall-within: close-range separation answered too "
        "strong rather than too weak (default: off)",
    )
    t.add_argument(
        "--shortfall-within",
        type=float,
        default=1.2,
        metavar="M",
        help="nearest-neighbour distance under which --weight-shortfall applies (default 1.2 m)",
    )
    t.add_argument(
        "--weight-flock",
        type=float,
        default=None,
        metavar="LAMBDA",
        help="add the flock-sum term with this weight: per flock (one run, one time step) the "
        "squared sum of its drones' errors in the world frame, so an error the whole flock "
        "shares costs more; batches are drawn as whole flocks (default: off)",
    )
    t.add_argument(
        "--lr-schedule",
        choices=LR_SCHEDULES,
        default="plateau",
        help="plateau: the paper's (lr halved after 10 epochs without improvement); cosine: "
        "lr decays batch by batch to 0 over --max-epochs (anneals a short fine-tune)",
    )
    t.add_argument(
        "--separation-scale",
        type=float,
        default=1.0,
        metavar="S",
        help="learn the flocking law with its separation gain k_sep x S: every label (validation "
        "too) recomputed from the flock's stored positions; a student that keeps its margin on "
        "the cautious side (default 1: the recorded labels; range 0.5-2)",
    )
    t.add_argument(
        "--near-separation-scale",
        type=float,
        default=1.0,
        metavar="C",
        help="and the neighbours closer than --near-separation-radius weigh C in the separation "
        "sum: a close-range boost where the paper's law comes under 1 m (a flock contracting "
        "onto its migration point); labels recomputed as for --separation-scale (default 1; "
        "range 0.5-4)",
    )
    t.add_argument(
        "--near-separation-radius",
        type=float,
        default=1.2,
        metavar="M",
        help="the close-range boost's reach: neighbours closer than M metres (default 1.2; range "
        "0.5-5)",
    )
    t.add_argument(
        "--separation-radius",
        type=float,
        default=None,
        metavar="M",
        help="k_sep x S for the neighbours closer than M metres only, the paper's law for the "
        "far ones (default: every neighbour; range 0.5-20, at least --near-separation-radius)",
    )
    t.add_argument(
        "--near-separation-ramp",
        type=float,
        default=0.0,
        metavar="W",
        help="the boost ramps in over W metres inside its reach: a neighbour's weight rises "
        "linearly from 1 at the reach to C at the reach - W (default 0: a step at the reach, "
        "which a network answers blurred; range 0-2, shorter than the reach)",
    )
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(handler=_train)

    e = sub.add_parser("evaluate", help="MSE, RMSE, R² and error breakdown on a dataset split")
    e.add_argument("--model", type=Path, default=SHIPPED_MODEL_PATH, help="policy or checkpoint")
    e.add_argument("--dataset", type=Path, required=True)
    e.add_argument("--split", choices=SPLITS, default="test")
    e.add_argument("--out", type=Path, default=None, help="default runs/eval/<model>-<split>")
    e.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu")
    e.add_argument("--batch-size", type=int, default=512)
    e.set_defaults(handler=_evaluate)

    x = sub.add_parser("export", help="evaluate a checkpoint on the test split, write the policy")
    x.add_argument("--checkpoint", type=Path, required=True, help="run folder or .ckpt")
    x.add_argument("--dataset", type=Path, required=True, help="the dataset it was trained on")
    x.add_argument("--out", type=Path, default=SHIPPED_MODEL_PATH, help="policy file (.pt)")
    x.add_argument("--eval-out", type=Path, default=None, help="default runs/eval/<out>-test")
    x.add_argument(
        "--symmetry",
        choices=tuple(GROUPS),
        default="none",
        help="average the network over the rig's symmetric views of each image (one batch of "
        "2, 4 or 8 per image; exactly equivariant, a body-frame bias cancels; default none)",
    )
    x.add_argument(
        "--output-gain",
        type=float,
        default=1.0,
        help="multiply the network's answers by this (its head's weights), recorded in the "
        "metadata; > 1 undoes the shrinking of large commands (docs: models/README.md; "
        "default 1, range 0.5-2)",
    )
    x.set_defaults(handler=_export)

    add_combining_commands(sub)

    g = sub.add_parser("gradcam", help="Grad-CAM saliency PNGs for dataset samples")
    g.add_argument("--model", type=Path, default=SHIPPED_MODEL_PATH, help="policy or checkpoint")
    g.add_argument("--dataset", type=Path, required=True)
    g.add_argument("--split", choices=SPLITS, default="test")
    g.add_argument("--samples", type=_samples, default=[0], help="indices, e.g. 0,5,9")
    g.add_argument(
        "--target",
        choices=("all", "speed", "x", "y", "z"),
        default="all",
        help="scalar explained: |v|, or one body axis' |v_k| (default all four rows)",
    )
    g.add_argument("--out", type=Path, default=Path("runs/gradcam"))
    g.set_defaults(handler=_gradcam)


def _train(args: argparse.Namespace) -> int:
    from sim_harness.learning.train import TrainConfig, train

    out_dir = require_writable_dir(args.out or Path("runs/train") / args.dataset.name)
    config = TrainConfig(
        dataset=args.dataset,
        out_dir=out_dir,
        max_epochs=args.max_epochs,
        batch_size=args.batch_size,
        lr=args.lr,
        dropout=args.dropout,
        seed=args.seed,
        device=args.device,
        threads=args.threads,
        limit_train=args.limit_train,
        limit_val=args.limit_val,
        resume=args.resume,
        extra_train=tuple(args.extra_train),
        init_from=args.init_from,
        arch=args.arch,
        augment=args.augment,
        weight_speed_mps=args.weight_speed,
        weight_near_m=args.weight_near,
        weight_cap=args.weight_cap,
        weight_shortfall=args.weight_shortfall,
        shortfall_within_m=args.shortfall_within,
        weight_flock=args.weight_flock,
        lr_schedule=args.lr_schedule,
        separation_scale=args.separation_scale,
        near_separation_scale=args.near_separation_scale,
        near_separation_radius_m=args.near_separation_radius,
        near_separation_ramp_m=args.near_separation_ramp,
        separation_radius_m=args.separation_radius,
        progress=not args.no_progress,
        command=command_line(),
    )
    result = train(config)
    how = "stopped early" if result.stopped_early else "reached the epoch limit"
    print(
        f"{how} after {result.epochs_run} epochs ({result.wall_time_s / 60:.1f} min): best "
        f"validation MSE {result.best_val_loss:.4f} (m/s)² at epoch {result.best_epoch} "
        f"(untrained {result.initial_val_loss:.4f})"
    )
    print(f"wrote {result.out_dir}/ (best.ckpt, last.ckpt, metrics.jsonl, learning_curve.png)")
    return 0


def _describe_metrics(metrics: dict[str, Any]) -> str:
    def r2(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.3f}"

    axes = ", ".join(f"{axis} {r2(m['r2'])}" for axis, m in metrics["per_axis"].items())
    overall = metrics["overall"]
    return (
        f"n = {metrics['n_samples']}: RMSE {overall['rmse']:.3f} m/s, R² {r2(overall['r2'])} "
        f"(per axis: {axes})"
    )


def _evaluate(args: argparse.Namespace) -> int:
    from sim_harness.dataset.store import open_dataset
    from sim_harness.learning.evaluate import evaluate_split
    from sim_harness.learning.export import load_for_inference
    from sim_harness.learning.train import resolve_device

    device = resolve_device(args.device)
    model, _ = load_for_inference(args.model, device)
    split = open_dataset(args.dataset).split(args.split)
    out = require_writable_dir(args.out or Path("runs/eval") / f"{args.model.stem}-{args.split}")
    report = evaluate_split(
        model, split, out, args.batch_size, device, title=f"{args.model} on {args.split}"
    )
    print(_describe_metrics(report["metrics"]))
    print(f"wrote {out}/ (metrics.json, predictions.npz, pred_vs_target.png, error_breakdown.png)")
    return 0


def _export(args: argparse.Namespace) -> int:
    from sim_harness.dataset.store import open_dataset
    from sim_harness.learning.checkpoint import LAST_NAME, CheckpointError, load_checkpoint
    from sim_harness.learning.export import (
        checkpoint_chain,
        load_eager_model,
        require_output_gain,
        scale_output,
    )

    if args.out.suffix != ".pt":
        raise ConfigError(f"out: the policy file must end in .pt, got {args.out}")
    require_output_gain(args.output_gain)  # before anything is read
    eval_out = args.eval_out or Path("runs/eval") / f"{args.out.stem}-test"
    require_writable_dir(args.out.parent)
    require_writable_dir(eval_out, "eval-out")
    model, state = load_eager_model(args.checkpoint)
    scale_output(model, args.output_gain)
    dataset = open_dataset(args.dataset)
    if state["dataset"]["id"] != dataset.id:
        raise CheckpointError(
            f"{args.checkpoint} was trained on dataset {state['dataset']['id']}, "
            f"but {args.dataset} is {dataset.id}"
        )
    run_dir = args.checkpoint if args.checkpoint.is_dir() else args.checkpoint.parent
    last = load_checkpoint(run_dir / LAST_NAME) if (run_dir / LAST_NAME).exists() else state
    training = {
        "command": state["command"],
        "epochs_run": last["epoch"],
        "best_epoch": state["best_epoch"],
        "best_val_mse": state["best_val_loss"],
        "initial_val_mse": state["initial_val_loss"],
        "wall_time_s": last["wall_time_s"],
        "config": state["config"],
        "output_gain": args.output_gain,
        **checkpoint_chain(state),
    }
    _evaluate_and_write(model, dataset, training, args.out, eval_out, args.symmetry)
    return 0


def _evaluate_and_write(
    model: Any, dataset: Any, training: dict[str, Any], out: Path, eval_out: Path, symmetry: str
) -> None:
    """Export `model` as the policy file `out`: its graph evaluated on `dataset`'s test split
    (report in `eval_out`), the result and `training` recorded in its metadata."""
    import torch

    from sim_harness.learning.evaluate import evaluate_split
    from sim_harness.learning.export import export_policy, to_torchscript

    scripted = to_torchscript(model, symmetry=symmetry)
    test = dataset.split("test")
    report = evaluate_split(scripted, test, eval_out, title=f"{out.name} on test")
    result = export_policy(
        model,
        out,
        dataset.manifest,
        {"split": "test", **report},
        training,
        scripted=scripted,
        check_images_u8=torch.from_numpy(test.images[: min(16, test.n_samples)].copy()),
        symmetry=symmetry,
    )
    print(f"test {_describe_metrics(report['metrics'])}")
    print(
        f"wrote {result.path} (sha256 {result.sha256[:16]}..., exported vs eager "
        f"{result.max_abs_diff_mps:.1e} m/s), {result.path.with_suffix('.json').name}, "
        f"{result.weights_path.name}; evaluation in {eval_out}/"
    )


def _gradcam(args: argparse.Namespace) -> int:
    from sim_harness.dataset.store import open_dataset
    from sim_harness.learning.ensemble import load_eager_policy
    from sim_harness.learning.gradcam import TARGETS, grad_cam, save_gradcam_png

    model, _ = load_eager_policy(args.model)
    split = open_dataset(args.dataset).split(args.split)
    require_writable_dir(args.out)
    bad = [i for i in args.samples if i >= split.n_samples]
    if bad:
        raise ConfigError(
            f"samples: {bad} outside the allowed range [0, {split.n_samples - 1}] "
            f"of the {args.split} split"
        )
    targets = TARGETS if args.target == "all" else (args.target,)
    meta = split.meta
    for i in args.samples:
        image = split.images[i]
        maps = {}
        for target in targets:
            result = grad_cam(model, image, target)
            maps["|v|" if target == "speed" else f"|v_{target}|"] = result.heatmap[0]
        pred = result.vel_body_flu[0]
        truth = split.targets[i]
        title = (
            f"{args.split} sample {i}: predicted ({pred[0]:+.2f}, {pred[1]:+.2f}, "
            f"{pred[2]:+.2f}) m/s, target ({truth[0]:+.2f}, {truth[1]:+.2f}, {truth[2]:+.2f}) "
            "m/s body FLU"
        )
        if "n_neighbours" in meta and "nearest_m" in meta:
            neighbours, nearest_m = int(meta["n_neighbours"][i]), float(meta["nearest_m"][i])
            title += f"; {neighbours} neighbours, nearest {nearest_m:.1f} m"
        path = save_gradcam_png(image, maps, args.out / f"{args.split}-{i:06d}.png", title)
        print(f"wrote {path}")
    return 0
