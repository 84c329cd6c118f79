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
batch norm and zero-initialized head (see `sim_harness.model`); it is kept against rare
start-up spikes, and `metrics.jsonl` records the fraction of clipped steps per epoch.

A run directory holds `last.ckpt` (written every epoch, for `resume`), `best.ckpt` (lowest
validation loss), `metrics.jsonl` (one JSON object per epoch), `learning_curve.png` and
`config.json`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from companion.errors import ConfigError
from companion.validation import require_int_range, require_positive, require_range
from sim_harness.batches import (
    SplitArrays,
    load_batch,
    prefetch,
    shuffled_batches,
    subset,
)
from sim_harness.checkpoint import (
    BEST_NAME,
    LAST_NAME,
    CheckpointError,
    load_checkpoint,
    restore_rng_state,
    rng_state,
    save_checkpoint,
)
from sim_harness.evaluate import predict
from sim_harness.model import DroNet, build_model, parameter_groups

log = logging.getLogger(__name__)

DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class TrainConfig:
    """One training run. Defaults are the paper's hyper-parameters."""

    dataset: Path
    out_dir: Path
    max_epochs: int = 200
    batch_size: int = 128
    lr: float = 5e-3
    momentum: float = 0.9
    weight_decay: float = 5e-4
    dropout: float = 0.5
    grad_clip_norm: float | None = 10.0  # not in the paper: see the module docstring
    lr_factor: float = 0.5
    lr_patience_epochs: int = 10  # lr x lr_factor after this many epochs without improvement
    early_stop_patience_epochs: int = 10  # stop after MORE than this many without improvement
    seed: int = 0
    device: str = "auto"
    limit_train: int | None = None  # quick runs: a fixed random subset of the training split
    limit_val: int | None = None
    eval_batch_size: int = 512
    ram_max_gib: float = 4.0  # a split (or subset) up to this size is copied into RAM
    threads: int | None = None  # torch CPU threads (None: torch's default)
    progress: bool = True
    resume: bool = False
    command: str = ""  # the command line that started the run, recorded in checkpoints

    def __post_init__(self) -> None:
        require_int_range("max_epochs", self.max_epochs, 1)
        require_int_range("batch_size", self.batch_size, 1)
        require_positive("lr", self.lr)
        require_range("momentum", self.momentum, 0.0, 1.0, high_inclusive=False)
        require_range("weight_decay", self.weight_decay, 0.0, 1.0)
        require_range("dropout", self.dropout, 0.0, 1.0, high_inclusive=False)
        if self.grad_clip_norm is not None:
            require_positive("grad_clip_norm", self.grad_clip_norm)
        require_range("lr_factor", self.lr_factor, 0.0, 1.0, low_inclusive=False)
        require_int_range("lr_patience_epochs", self.lr_patience_epochs, 1)
        require_int_range("early_stop_patience_epochs", self.early_stop_patience_epochs, 0)
        require_int_range("seed", self.seed, 0)
        if self.device not in DEVICES:
            raise ConfigError(f"device: {self.device!r} is not one of {', '.join(DEVICES)}")
        for name in ("limit_train", "limit_val"):
            value = getattr(self, name)
            if value is not None:
                require_int_range(name, value, 1)
        require_int_range("eval_batch_size", self.eval_batch_size, 1)
        require_range("ram_max_gib", self.ram_max_gib, 0.0, None)
        if self.threads is not None:
            require_int_range("threads", self.threads, 1, 1024)

    def as_dict(self) -> dict[str, Any]:
        """Plain data (paths as strings) for JSON and checkpoints."""
        return {
            k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(self).items()
        }


@dataclass(frozen=True)
class TrainResult:
    """What a finished (or stopped) run achieved; `history` is one dict per epoch."""

    out_dir: Path
    epochs_run: int
    best_epoch: int
    best_val_loss: float
    initial_val_loss: float
    stopped_early: bool
    wall_time_s: float
    history: list[dict[str, Any]] = field(repr=False)

    @property
    def best_checkpoint(self) -> Path:
        return self.out_dir / BEST_NAME


def resolve_device(name: str) -> torch.device:
    """ "auto" -> CUDA when available, else CPU; "cuda" without a GPU is a `ConfigError`."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device: 'cuda' was requested but torch sees no CUDA device")
    return torch.device(name)


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
    batches: list[np.ndarray],
    device: torch.device,
    grad_clip_norm: float | None,
    progress: bool,
    desc: str,
) -> tuple[float, float, float]:
    """One pass over `batches`; returns (mean training loss, samples/s, fraction clipped)."""
    model.train()
    pin = device.type == "cuda"
    total = torch.zeros((), dtype=torch.float64, device=device)
    clipped = torch.zeros((), dtype=torch.int64, device=device)
    seen = 0
    start = time.perf_counter()
    with tqdm(
        total=sum(len(rows) for rows in batches),
        desc=desc,
        unit="img",
        unit_scale=True,
        leave=False,
        disable=not progress,
    ) as bar:
        for step, (images, targets) in enumerate(
            prefetch(load_batch(split, rows, pin) for rows in batches)
        ):
            images = images.to(device, non_blocking=True)
            targets = targets.to(device, non_blocking=True)
            loss = velocity_loss(model(images), targets)
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
    return train_on(config, dataset.manifest, dataset.split("train"), dataset.split("val"))


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
    val_data = subset(val_split, config.limit_val, config.seed + 1, ram_max)
    out = config.out_dir
    out.mkdir(parents=True, exist_ok=True)

    torch.manual_seed(config.seed)
    model = build_model(manifest["pixel_mean"], manifest["pixel_std"], config.dropout, device)
    optimizer = torch.optim.SGD(
        parameter_groups(model, config.weight_decay),  # type: ignore[arg-type]
        lr=config.lr,
        momentum=config.momentum,
    )
    scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
        optimizer,
        mode="min",
        factor=config.lr_factor,
        patience=config.lr_patience_epochs - 1,  # torch halves on the (patience + 1)-th bad epoch
        threshold=0.0,
    )
    state: dict[str, Any] = {
        "epoch": 0,
        "best_val_loss": float("inf"),
        "best_epoch": 0,
        "epochs_since_best": 0,
        "history": [],
        "dataset": {"id": manifest["id"], "root": str(config.dataset)},
        "command": config.command,
        "initial_val_loss": float("nan"),
        "wall_time_s": 0.0,
    }
    if config.resume:
        state = _resume(out / LAST_NAME, manifest, model, optimizer, scheduler, device)
    else:
        state["initial_val_loss"] = validation_loss(model, val_data, config.eval_batch_size, device)
    (out / "config.json").write_text(
        json.dumps(
            {
                "config": config.as_dict(),
                "dataset_id": manifest["id"],
                "from_epoch": state["epoch"],
            },
            indent=2,
        )
        + "\n"
    )
    history: list[dict[str, Any]] = state["history"]
    run_start = time.perf_counter() - state["wall_time_s"]
    stopped_early = state["epochs_since_best"] > config.early_stop_patience_epochs
    epoch = state["epoch"]
    while not stopped_early and epoch < config.max_epochs:
        epoch += 1
        epoch_start = time.perf_counter()
        batches = shuffled_batches(train_data.n_samples, config.batch_size, config.seed, epoch)
        train_loss, samples_per_s, clipped = _train_epoch(
            model,
            optimizer,
            train_data,
            batches,
            device,
            config.grad_clip_norm,
            config.progress,
            f"epoch {epoch}/{config.max_epochs}",
        )
        val_loss = validation_loss(model, val_data, config.eval_batch_size, device)
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step(val_loss)
        improved = val_loss < state["best_val_loss"]
        if improved:
            state.update(best_val_loss=val_loss, best_epoch=epoch, epochs_since_best=0)
        else:
            state["epochs_since_best"] += 1
        stopped_early = state["epochs_since_best"] > config.early_stop_patience_epochs
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
            epoch=epoch,
            model=model.state_dict(),
            model_config={
                "pixel_mean": float(manifest["pixel_mean"]),
                "pixel_std": float(manifest["pixel_std"]),
                "dropout": config.dropout,
            },
            optimizer=optimizer.state_dict(),
            scheduler=scheduler.state_dict(),
            rng=rng_state(),
            config=config.as_dict(),
            wall_time_s=time.perf_counter() - run_start,
        )
        save_checkpoint(state, out / LAST_NAME)
        if improved:
            save_checkpoint(state, out / BEST_NAME)
        _write_metrics(history, out / "metrics.jsonl")
        _write_learning_curve(history, state["initial_val_loss"], out)
        log.info(
            "epoch %d: train %.4f, val %.4f (best %.4f at %d), lr %.2g, %.0f samples/s",
            epoch,
            train_loss,
            val_loss,
            state["best_val_loss"],
            state["best_epoch"],
            lr,
            samples_per_s,
        )
    return TrainResult(
        out_dir=out,
        epochs_run=epoch,
        best_epoch=state["best_epoch"],
        best_val_loss=state["best_val_loss"],
        initial_val_loss=state["initial_val_loss"],
        stopped_early=stopped_early,
        wall_time_s=time.perf_counter() - run_start,
        history=history,
    )


def _resume(
    path: Path,
    manifest: dict[str, Any],
    model: DroNet,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.ReduceLROnPlateau,
    device: torch.device,
) -> dict[str, Any]:
    """Load `path` into model, optimizer, scheduler and RNG; return the checkpoint's state."""
    if not path.exists():
        raise CheckpointError(f"cannot resume: {path} does not exist")
    state = load_checkpoint(path, map_location=device)
    if state["dataset"]["id"] != manifest["id"]:
        raise CheckpointError(
            f"cannot resume: {path} was trained on dataset {state['dataset']['id']}, "
            f"not {manifest['id']}"
        )
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    restore_rng_state(state["rng"])
    log.info("resumed %s after epoch %d", path, state["epoch"])
    return state


def _write_metrics(history: list[dict[str, Any]], path: Path) -> None:
    path.write_text("".join(json.dumps(row) + "\n" for row in history))


def _write_learning_curve(history: list[dict[str, Any]], initial: float, out: Path) -> None:
    from sim_harness.learn_plots import save_learning_curve

    save_learning_curve(history, initial, out / "learning_curve.png")
