"""Training the policy network with the paper's recipe.

Loss: mean squared error over the batch and the three body axes, (m/s)^2 (the data term of the
paper's eq. 1, averaged over the axes as Keras' `mse`; its `(lambda / 2) ||w||^2` term is SGD's
weight decay `lambda` on the conv and linear weights only). SGD with momentum 0.9, lr 5e-3 halved
once the validation loss has not improved for 10 consecutive epochs, batch 128, dropout 0.5;
training stops once the validation loss has not improved for more than 10 consecutive epochs (or
at `max_epochs`). Inputs are standardized inside the model with the training split's pixel mean
and standard deviation from the dataset manifest.

One safeguard the paper does not state: the gradient's global norm is clipped at
`grad_clip_norm` (10 by default; None turns it off). It was needed before the model got its final
batch norm and zero-initialized head (see `sim_harness.learning.model`); it is kept against rare
start-up spikes, and `metrics.jsonl` records the fraction of clipped steps per epoch.

Optional terms beyond the paper: `weight_speed_mps` weights each sample's error by the size of its
command and `weight_near_m` by how close its nearest neighbour is
(`sim_harness.learning.sample_weights`); `weight_flock` adds the flock-sum term
(`sim_harness.learning.flock_loss`: the error a whole flock shares at one time step), and then
batches are drawn as whole flocks.

A run directory holds `last.ckpt` (written every epoch, for `resume`), `best.ckpt` (lowest
validation loss), `metrics.jsonl` (one JSON object per epoch), `learning_curve.png` and
`config.json`.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from companion.errors import ConfigError
from sim_harness.learning.batches import (
    SplitArrays,
    concat_splits,
    epoch_rows,
    load_batch,
    prefetch,
    shuffled_batches,
    subset,
    with_repeats,
)
from sim_harness.learning.checkpoint import (
    BEST_NAME,
    LAST_NAME,
    optimizer_state,
    resume_into,
    rng_state,
    save_checkpoint,
)
from sim_harness.learning.evaluate import predict
from sim_harness.learning.flock_loss import (
    PART_COLUMN,
    Batch,
    FlockLoss,
    flock_batches,
    flock_ids,
    flock_term,
    world_rotations,
)
from sim_harness.learning.model import DroNet, build_model
from sim_harness.learning.optimization import Plateau, cosine_lr_at, make_optimizer, make_scheduler
from sim_harness.learning.relabel import relabelled
from sim_harness.learning.sample_weights import SampleWeighting
from sim_harness.learning.symmetry import augment_with_views
from sim_harness.learning.train_config import TrainConfig, TrainResult, resolve_device
from sim_harness.sim.progress import progress_bar

__all__ = ["TrainConfig", "TrainResult", "resolve_device", "train", "train_on"]

log = logging.getLogger(__name__)

CURVE_EVERY_EPOCHS = 5  # learning_curve.png is redrawn this often, and when training ends


def velocity_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the batch and the three axes, (m/s)^2."""
    return (pred - target).square().mean()


def validation_loss(
    model: DroNet, split: SplitArrays, batch_size: int, device: torch.device
) -> float:
    """`velocity_loss` over a whole split, model in eval mode."""
    pred = predict(model, split.images, batch_size, device)
    return float(np.mean((pred - split.targets) ** 2, dtype=np.float64))


def _train_epoch(
    model: DroNet,
    optimizer: torch.optim.Optimizer,
    split: SplitArrays,
    batches: list[Batch],
    device: torch.device,
    grad_clip_norm: float | None,
    progress: bool,
    desc: str,
    augment_group: str = "none",
    augment_seed: tuple[int, int] = (0, 0),
    weighting: SampleWeighting | None = None,
    lr_at: Callable[[int], float] | None = None,
    flock: FlockLoss | None = None,
) -> tuple[float, float, float]:
    """One pass over `batches`; returns (mean training loss, samples/s, fraction clipped).

    `weighting`: the per-sample loss weights, or None for the plain mean squared error; the
    returned loss is the one minimized (weighted when weighting). A close-range weighting and the
    shortfall term read the split's "nearest_m" column.

    `augment_group`: each sample is shown in a random view of this symmetry group with its label
    transformed to match (`learning.symmetry.augment`), drawn from a generator seeded by
    `augment_seed` (the run's seed and the epoch: a resumed epoch sees the same views).

    `lr_at`: the lr of each batch by its index in the epoch (None: the optimizer's own).

    `flock`: add the flock-sum term with this weight; `batches` are then (rows, batch-local
    flock index) pairs of whole flocks (`flock_loss.flock_batches`).
    """
    model.train()
    pin = device.type == "cuda"
    generator = torch.Generator().manual_seed(augment_seed[0] * 1_000_003 + augment_seed[1])

    def batch(item: Batch) -> tuple[torch.Tensor, ...]:
        rows, local = item if isinstance(item, tuple) else (item, None)
        images, targets = load_batch(split, rows)
        images, targets, views = augment_with_views(images, targets, generator, augment_group)
        # the symmetries move no drone, so the nearest neighbour's distance stays the sample's
        nearest = torch.from_numpy(
            np.asarray(split.meta["nearest_m"][rows], dtype=np.float32)
            if weighting is not None and weighting.needs_nearest
            else np.zeros(0, dtype=np.float32)
        )
        tensors: tuple[torch.Tensor, ...] = (images, targets, nearest)
        if flock is not None and local is not None:
            tensors = (*tensors, flock.view_to_world(rows, views), torch.from_numpy(local))
        if pin:
            tensors = tuple(t.pin_memory() for t in tensors)
        return tensors

    total = torch.zeros((), dtype=torch.float64, device=device)
    clipped = torch.zeros((), dtype=torch.int64, device=device)
    seen = 0
    start = time.perf_counter()
    with progress_bar(
        total=sum(len(rows) for rows in batches),
        desc=desc,
        enabled=progress,
        unit="img",
        unit_scale=True,
        leave=False,
    ) as bar:
        for step, tensors in enumerate(prefetch(batch(item) for item in batches)):
            images, targets, nearest, *flock_tensors = (
                t.to(device, non_blocking=True) for t in tensors
            )
            pred = model(images)
            if weighting is None:
                loss = velocity_loss(pred, targets)
            else:
                loss = weighting.loss(pred, targets, nearest)
            if flock is not None:
                to_world, local = flock_tensors
                term = flock_term(pred - targets, to_world, local, int(local.max().item()) + 1)
                loss = (loss + flock.weight * term) / (1.0 + flock.weight)
            if lr_at is not None:
                for group in optimizer.param_groups:
                    group["lr"] = lr_at(step)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()  # type: ignore[no-untyped-call]
            if grad_clip_norm is not None:
                norm = torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip_norm)
                clipped += norm > grad_clip_norm
            optimizer.step()
            n = targets.shape[0]
            total += loss.detach().double() * n
            seen += n
            bar.update(n)
            if progress and step % 10 == 0:
                bar.set_postfix(loss=f"{total.item() / seen:.4f}")
    elapsed = time.perf_counter() - start
    steps = max(len(batches), 1)
    return total.item() / max(seen, 1), seen / max(elapsed, 1e-9), clipped.item() / steps


def train(config: TrainConfig) -> TrainResult:
    """Open `config.dataset` (a generated dataset) and train on its train / val splits."""
    from sim_harness.dataset.store import open_dataset

    dataset = open_dataset(config.dataset)
    train_split: SplitArrays = dataset.split("train")
    if config.extra_train:
        # a folder named k times is loaded once and shown k times per epoch
        roots = list(dict.fromkeys(config.extra_train))
        parts = [train_split, *(open_dataset(root).split("train") for root in roots)]
        joined = concat_splits(parts)
        part_of_row = np.repeat(np.arange(len(parts)), [p.n_samples for p in parts])
        meta = {**joined.meta, PART_COLUMN: part_of_row}  # flocks never span two folders
        joined = replace(joined, meta=meta)
        times = [1] + [config.extra_train.count(root) for root in roots]
        counts = np.repeat(times, [part.n_samples for part in parts]).astype(np.int64)
        train_split = with_repeats(joined, counts) if max(times) > 1 else joined
        log.info(
            "training on %s plus %s: %d samples, %d per epoch",
            config.dataset,
            ", ".join(
                f"{r} (x{k})" if k > 1 else str(r) for r, k in zip(roots, times[1:], strict=True)
            ),
            train_split.n_samples,
            int(counts.sum()),
        )
    val_split: SplitArrays = dataset.split("val")
    if config.separation_scale != 1.0 or config.near_separation_scale != 1.0:
        scale, near, reach, ramp, scaled = (
            config.separation_scale,
            config.near_separation_scale,
            config.near_separation_radius_m,
            config.near_separation_ramp_m,
            config.separation_radius_m,
        )
        law = (near, reach, ramp, scaled)
        train_split = relabelled(train_split, scale, "the training data", *law)
        val_split = relabelled(val_split, scale, f"{config.dataset}'s val split", *law)
        log.info(
            "labels: the flocking law with k_sep x %g%s, neighbours within %g m x %g more%s",
            scale,
            "" if scaled is None else f" within {scaled:g} m",
            reach,
            near,
            f" (ramped in over {ramp:g} m)" if ramp > 0 else "",
        )
    return train_on(config, dataset.manifest, train_split, val_split)


def train_on(
    config: TrainConfig,
    manifest: dict[str, Any],
    train_split: SplitArrays,
    val_split: SplitArrays,
) -> TrainResult:
    """Train on given splits; `manifest` supplies "id", "pixel_mean" and "pixel_std"."""
    device = resolve_device(config.device)
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    ram_max = int(config.ram_max_gib * 2**30)
    train_data = subset(train_split, config.limit_train, config.seed, ram_max)
    rows = epoch_rows(train_data)
    needs_nearest = [
        name for name in ("weight_near_m", "weight_shortfall") if getattr(config, name) is not None
    ]
    if needs_nearest and "nearest_m" not in train_data.meta:
        raise ConfigError(
            f"{needs_nearest[0]}: the training data lacks the per-sample column nearest_m "
            "(a dataset written by `swarm-sim dataset generate` or `aggregate` has it)"
        )
    flock = None
    if config.weight_flock is not None:
        flock_id = flock_ids(train_data.meta)
        flock = FlockLoss(config.weight_flock, world_rotations(train_data.meta))
    val_data = subset(val_split, config.limit_val, config.seed + 1, ram_max)
    out = config.out_dir
    out.mkdir(parents=True, exist_ok=True)

    torch.manual_seed(config.seed)
    model = build_model(
        manifest["pixel_mean"], manifest["pixel_std"], config.dropout, device, config.arch
    )
    optimizer = make_optimizer(model, config)
    scheduler = make_scheduler(optimizer, config)
    plateau = Plateau(config.early_stop_patience_epochs)
    state: dict[str, Any] = {
        "epoch": 0,
        "history": [],
        "dataset": {"id": manifest["id"], "root": str(config.dataset)},
        "command": config.command,
        "wall_time_s": 0.0,
        "train_samples": train_data.n_samples,
        "epoch_samples": len(rows),
        "model_config": {
            "pixel_mean": float(manifest["pixel_mean"]),
            "pixel_std": float(manifest["pixel_std"]),
            "dropout": config.dropout,
            "arch": config.arch,
        },
    }
    if config.resume:
        state = resume_into(out / LAST_NAME, manifest, model, optimizer, scheduler, device)
        plateau.restore(state)
    else:
        if config.init_from is not None:
            _init_weights(model, config.init_from, state)
        state["initial_val_loss"] = validation_loss(model, val_data, config.eval_batch_size, device)
    info = {"config": config.as_dict(), "dataset_id": manifest["id"], "from_epoch": state["epoch"]}
    (out / "config.json").write_text(json.dumps(info, indent=2) + "\n")
    history: list[dict[str, Any]] = state["history"]
    run_start = time.perf_counter() - state["wall_time_s"]
    epoch = state["epoch"]
    while not plateau.stop and epoch < config.max_epochs:
        epoch += 1
        epoch_start = time.perf_counter()
        batches: list[Batch] = (
            list(shuffled_batches(len(rows), config.batch_size, config.seed, epoch, rows))
            if flock is None
            else list(flock_batches(flock_id, rows, config.batch_size, config.seed, epoch))
        )
        cosine = config.lr_schedule == "cosine"
        lr_at = cosine_lr_at(config, epoch, len(batches)) if cosine else None
        train_loss, samples_per_s, clipped = _train_epoch(
            model,
            optimizer,
            train_data,
            batches,
            device,
            config.grad_clip_norm,
            config.progress,
            f"epoch {epoch}/{config.max_epochs}",
            config.augment,
            (config.seed, epoch),
            SampleWeighting.of(config),
            lr_at,
            flock,
        )
        val_loss = validation_loss(model, val_data, config.eval_batch_size, device)
        lr = optimizer.param_groups[0]["lr"]  # the epoch's last batch's
        if config.lr_schedule == "plateau":
            scheduler.step(val_loss)
        improved = plateau.update(epoch, val_loss)
        history.append(
            {
                "epoch": epoch,
                "train_loss": train_loss,
                "val_loss": val_loss,
                "val_rmse_mps": float(np.sqrt(val_loss)),
                "lr": lr,
                "train_samples_per_s": samples_per_s,
                "clipped_fraction": clipped,
                "epoch_wall_s": time.perf_counter() - epoch_start,
                "improved": improved,
            }
        )
        state.update(
            plateau.as_state(),
            epoch=epoch,
            model=model.state_dict(),
            optimizer=optimizer_state(optimizer, model),
            scheduler=scheduler.state_dict(),
            rng=rng_state(),
            config=config.as_dict(),
            wall_time_s=time.perf_counter() - run_start,
        )
        save_checkpoint(state, out / LAST_NAME)
        if improved:
            save_checkpoint(state, out / BEST_NAME)
        _write_metrics(history, out / "metrics.jsonl")
        if epoch % CURVE_EVERY_EPOCHS == 0:
            _write_learning_curve(history, state["initial_val_loss"], out)
        log.info(
            "epoch %d: train %.4f, val %.4f (best %.4f at %d), lr %.2g, %.0f samples/s",
            epoch,
            train_loss,
            val_loss,
            plateau.best_val_loss,
            plateau.best_epoch,
            lr,
            samples_per_s,
        )
    if history:
        _write_learning_curve(history, state["initial_val_loss"], out)
    return TrainResult(
        out_dir=out,
        epochs_run=epoch,
        best_epoch=plateau.best_epoch,
        best_val_loss=plateau.best_val_loss,
        initial_val_loss=state["initial_val_loss"],
        stopped_early=plateau.stop,
        wall_time_s=time.perf_counter() - run_start,
        history=history,
    )


def _init_weights(model: DroNet, source: Path, state: dict[str, Any]) -> None:
    """Load `source`'s weights (checkpoint or policy file) into `model` for fine-tuning.

    The standardization comes along with the weights (they were trained with it); the run's
    `model_config` records it.
    """
    from sim_harness.learning.export import ancestor_chain, load_eager_model

    init, _ = load_eager_model(Path(source), device=next(model.parameters()).device)
    model.load_state_dict(init.state_dict())
    state["model_config"]["pixel_mean"] = float(init.standardize.pixel_mean)
    state["model_config"]["pixel_std"] = float(init.standardize.pixel_std)
    state["init_from"] = str(source)
    state["init_chain"] = ancestor_chain(str(source))  # before anything overwrites the source
    log.info("initialized from %s", source)


def _write_metrics(history: list[dict[str, Any]], path: Path) -> None:
    path.write_text("".join(json.dumps(row) + "\n" for row in history))


def _write_learning_curve(history: list[dict[str, Any]], initial: float, out: Path) -> None:
    from sim_harness.learning.plots import save_learning_curve

    save_learning_curve(history, initial, out / "learning_curve.png")
