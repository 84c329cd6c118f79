"""Configuration and result of a training run, and the device choice (see `learning.train`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from companion.errors import ConfigError
from companion.validation import require_int_range, require_positive, require_range
from sim_harness.learning.lr_schedule import LR_SCHEDULES
from sim_harness.learning.model import require_arch
from sim_harness.learning.symmetry_views import require_group

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
    # aggregated datasets (`swarm-sim dataset aggregate`) whose training splits join `dataset`'s;
    # validation stays on `dataset`'s own split, so runs stay comparable; a folder listed k times
    # is loaded once and its samples shown k times per epoch (weighting a targeted round)
    extra_train: tuple[Path, ...] = ()
    init_from: Path | None = None  # start from these weights (checkpoint or policy file)
    # the network (`learning.model.ARCHS`): "cube" pads each cube-map face with its neighbours;
    # both have the same weights, so either initializes the other
    arch: str = "dronet"
    # show each training sample in a random view of this symmetry group of the camera rig, label
    # transformed to match (`sim_harness.learning.symmetry`); "none": the images as recorded
    augment: str = "none"
    # weight each sample's squared error by max(1, |target| / weight_speed_mps), capped at
    # `weight_cap`, so the rare large commands (a neighbour close by, a stretched flock) are not
    # shrunk towards the mean; None: the paper's plain mean squared error
    weight_speed_mps: float | None = None
    # weight each sample's squared error by (weight_near_m / nearest)^4 where its nearest
    # neighbour is closer than weight_near_m, capped at `weight_cap`: the rare close-range states,
    # where a pair's safety is decided, weigh as much as the largest commands (with
    # weight_speed_mps too, a sample takes the larger of its two weights); None: off
    weight_near_m: float | None = None
    weight_cap: float = 4.0
    # add weight_shortfall x the squared shortfall of the answer along the teacher's command
    # on samples whose nearest neighbour is closer than shortfall_within_m
    # (`sample_weights.shortfall`): where the image leaves the distance uncertain, answer the
    # separation too strong rather than too weak; None: off
    weight_shortfall: float | None = None
    shortfall_within_m: float = 1.2
    # add the flock-sum term (`sim_harness.learning.flock_loss`) with this weight: errors that a
    # whole flock shares at one time step cost more than independent ones; None: off
    weight_flock: float | None = None
    # "plateau" (the paper's) or "cosine" (`sim_harness.learning.lr_schedule`)
    lr_schedule: str = "plateau"
    # learn the flocking law with its separation gain times this (`sim_harness.learning.relabel`:
    # every label, validation's too, recomputed from the stored positions); 1: the recorded labels
    separation_scale: float = 1.0
    # and the neighbours closer than `near_separation_radius_m` weigh this in its separation sum:
    # a close-range boost (1: the law's own weighting)
    near_separation_scale: float = 1.0
    near_separation_radius_m: float = 1.2  # `relabel.NEAR_M`
    # the boost ramps in over this many metres inside its reach (0: a step at the reach)
    near_separation_ramp_m: float = 0.0  # `relabel.RAMP_M`
    # k_sep x separation_scale for the neighbours within this many metres (None: every one)
    separation_radius_m: float | None = None  # `relabel.SCALE_REACH_M`

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
        require_group(self.augment, "augment")
        require_arch(self.arch)
        if self.weight_speed_mps is not None:
            require_positive("weight_speed_mps", self.weight_speed_mps)
        if self.weight_near_m is not None:
            require_range("weight_near_m", self.weight_near_m, 0.0, 20.0, low_inclusive=False)
        require_range("weight_cap", self.weight_cap, 1.0, None)
        if self.weight_shortfall is not None:
            require_range(
                "weight_shortfall", self.weight_shortfall, 0.0, 100.0, low_inclusive=False
            )
        require_range("shortfall_within_m", self.shortfall_within_m, 0.0, 20.0, low_inclusive=False)
        if self.weight_flock is not None:
            require_range("weight_flock", self.weight_flock, 0.0, 100.0, low_inclusive=False)
        require_range("separation_scale", self.separation_scale, 0.5, 2.0)
        require_range("near_separation_scale", self.near_separation_scale, 0.5, 4.0)
        require_range("near_separation_radius_m", self.near_separation_radius_m, 0.5, 5.0)
        require_range("near_separation_ramp_m", self.near_separation_ramp_m, 0.0, 2.0)
        if self.separation_radius_m is not None:
            require_range("separation_radius_m", self.separation_radius_m, 0.5, 20.0)
            if self.separation_radius_m < self.near_separation_radius_m:
                raise ConfigError(
                    f"separation_radius_m: {self.separation_radius_m:g} m must reach at least "
                    f"near_separation_radius_m ({self.near_separation_radius_m:g} m), the "
                    "boost's reach, which the scale also applies to"
                )
        if self.near_separation_ramp_m >= self.near_separation_radius_m:
            raise ConfigError(
                f"near_separation_ramp_m: {self.near_separation_ramp_m:g} m must be shorter than "
                f"near_separation_radius_m ({self.near_separation_radius_m:g} m), the boost's reach"
            )
        if self.lr_schedule not in LR_SCHEDULES:
            raise ConfigError(
                f"lr_schedule: {self.lr_schedule!r} is not one of {', '.join(LR_SCHEDULES)}"
            )
        if self.init_from is not None and self.resume:
            raise ConfigError("init_from: a resumed run continues from its own checkpoint")

    def as_dict(self) -> dict[str, Any]:
        """Plain data (paths as strings) for JSON and checkpoints."""

        def plain(v: Any) -> Any:
            if isinstance(v, Path):
                return str(v)
            return [plain(x) for x in v] if isinstance(v, tuple) else v

        return {k: plain(v) for k, v in dataclasses.asdict(self).items()}


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


def resolve_device(name: str) -> torch.device:
    """ "auto" -> CUDA when available, else CPU; "cuda" without a GPU is a `ConfigError`."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device: 'cuda' was requested but torch sees no CUDA device")
    return torch.device(name)
