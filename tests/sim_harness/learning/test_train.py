"""Training on the smoke dataset: it learns, checkpoints, resumes exactly and stops on time."""

import itertools
import json

import numpy as np
import pytest
import torch

from companion.errors import ConfigError
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.batches import InMemorySplit
from sim_harness.learning.checkpoint import (
    BEST_NAME,
    LAST_NAME,
    CheckpointError,
    load_checkpoint,
    load_optimizer_state,
    optimizer_state,
)
from sim_harness.learning.lr_schedule import cosine_lr
from sim_harness.learning.model import build_model
from sim_harness.learning.optimization import Plateau, make_optimizer, make_scheduler
from sim_harness.learning.sample_weights import (
    SampleWeighting,
    near_weights,
    shortfall,
    speed_weights,
    weighted_velocity_loss,
)
from sim_harness.learning.train import TrainConfig, train, train_on, velocity_loss


def quick(dataset, out, **overrides) -> TrainConfig:
    """A few small batches per epoch: seconds, not hours."""
    settings = {
        "batch_size": 32,
        "limit_train": 64,
        "limit_val": 32,
        "progress": False,
        **overrides,
    }
    return TrainConfig(dataset=dataset, out_dir=out, **settings)


@pytest.mark.slow
def test_a_short_training_lowers_the_validation_loss(smoke_dataset, tmp_path) -> None:
    # The whole smoke split, at a learning rate suited to 12 steps per epoch; the untrained
    # network (zero head) predicts 0 m/s, so beating it means learning from the images.
    config = TrainConfig(
        dataset=smoke_dataset,
        out_dir=tmp_path / "run",
        max_epochs=3,
        batch_size=32,
        lr=1e-3,
        progress=False,
    )
    result = train(config)
    assert result.epochs_run == 3
    assert result.best_val_loss < result.initial_val_loss
    assert result.history[-1]["train_loss"] < result.history[0]["train_loss"]
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    rows = [json.loads(line) for line in lines]
    assert [row["epoch"] for row in rows] == [1, 2, 3]
    for key in ("train_loss", "val_loss", "lr", "train_samples_per_s", "clipped_fraction"):
        assert all(np.isfinite(row[key]) for row in rows), key
    for name in (LAST_NAME, BEST_NAME, "learning_curve.png", "config.json"):
        assert (tmp_path / "run" / name).stat().st_size > 0, name
    best = load_checkpoint(tmp_path / "run")  # a run folder means its best checkpoint
    assert best["epoch"] == result.best_epoch and best["best_val_loss"] == result.best_val_loss
    assert best["dataset"]["id"] == open_dataset(smoke_dataset).id


def test_the_optimizer_decays_weights_only(smoke_dataset, tmp_path) -> None:
    train(quick(smoke_dataset, tmp_path, max_epochs=1, limit_train=32))
    state = load_checkpoint(tmp_path / LAST_NAME)
    model = build_model(state["model_config"]["pixel_mean"], state["model_config"]["pixel_std"])
    groups = state["optimizer"]["param_groups"]
    assert [g["weight_decay"] for g in groups] == [5e-4, 0.0]
    assert all(g["momentum"] == 0.9 and g["lr"] == 5e-3 for g in groups)
    # the saved groups list parameter indices in the order `parameter_groups` gave them
    weights = [n for n, p in model.named_parameters() if p.ndim > 1]
    others = [n for n, p in model.named_parameters() if p.ndim == 1]
    assert len(groups[0]["params"]) == len(weights) == 11
    assert len(groups[1]["params"]) == len(others)
    assert all(n.endswith((".bias", "bn1.weight", "bn2.weight", "bn_out.weight")) for n in others)
    optimizer = make_optimizer(model, quick(smoke_dataset, tmp_path))
    decayed = {id(p) for p in optimizer.param_groups[0]["params"]}
    assert {n for n, p in model.named_parameters() if id(p) in decayed} == set(weights)


def assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


@pytest.mark.slow
def test_resume_continues_from_the_checkpoint_epoch_and_state(smoke_dataset, tmp_path) -> None:
    straight = train(quick(smoke_dataset, tmp_path / "straight", max_epochs=2))
    train(quick(smoke_dataset, tmp_path / "split", max_epochs=1))
    first = load_checkpoint(tmp_path / "split" / LAST_NAME)
    assert first["epoch"] == 1
    resumed = train(quick(smoke_dataset, tmp_path / "split", max_epochs=2, resume=True))
    assert [row["epoch"] for row in resumed.history] == [1, 2]
    assert resumed.history[0] == first["history"][0]  # epoch 1 was not run again
    a = load_checkpoint(tmp_path / "straight" / LAST_NAME)
    b = load_checkpoint(tmp_path / "split" / LAST_NAME)
    assert a["epoch"] == b["epoch"] == 2
    assert_same_state(a["model"], b["model"])  # same batches, dropout masks and momentum
    assert a["scheduler"] == b["scheduler"]
    for pa, pb in zip(
        a["optimizer"]["state"].values(), b["optimizer"]["state"].values(), strict=True
    ):
        assert torch.equal(pa["momentum_buffer"], pb["momentum_buffer"])
    assert resumed.initial_val_loss == straight.initial_val_loss
    assert [r["val_loss"] for r in resumed.history] == [r["val_loss"] for r in straight.history]
    metrics = (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["epoch"] for line in metrics] == [1, 2]


def test_resume_refuses_another_dataset_or_a_missing_checkpoint(smoke_dataset, tmp_path) -> None:
    with pytest.raises(CheckpointError, match="does not exist"):
        train(quick(smoke_dataset, tmp_path / "none", resume=True))
    train(quick(smoke_dataset, tmp_path / "run", max_epochs=1, limit_train=32))
    split = open_dataset(smoke_dataset).split("train")
    manifest = {"id": "another-dataset", "pixel_mean": 180.0, "pixel_std": 35.0}
    config = quick(smoke_dataset, tmp_path / "run", max_epochs=2, resume=True)
    with pytest.raises(CheckpointError, match="another-dataset"):
        train_on(config, manifest, split, split)


def test_lr_halves_on_the_tenth_bad_epoch_and_training_stops_after_more_than_ten() -> None:
    config = TrainConfig(dataset=None, out_dir=None)  # type: ignore[arg-type]
    model = build_model(128.0, 64.0)
    optimizer = make_optimizer(model, config)
    scheduler = make_scheduler(optimizer, config)
    plateau = Plateau(config.early_stop_patience_epochs)
    losses = [1.0, 0.5] + [0.5] * 11  # a tie is no improvement
    lrs, stops = [], []
    for epoch, loss in enumerate(losses, start=1):
        scheduler.step(loss)
        plateau.update(epoch, loss)
        lrs.append(optimizer.param_groups[0]["lr"])
        stops.append(plateau.stop)
    assert lrs[:11] == [5e-3] * 11  # epochs 3..11: nine bad epochs, lr unchanged
    assert lrs[11] == 2.5e-3  # epoch 12: the tenth bad epoch in a row
    assert stops == [False] * 12 + [True]  # epoch 13: more than ten bad epochs
    assert plateau.best_epoch == 2 and plateau.best_val_loss == 0.5


def test_the_cosine_lr_falls_from_the_initial_lr_towards_zero_over_the_run() -> None:
    lrs = [cosine_lr(1e-3, step, 1000) for step in range(1000)]
    assert lrs[0] == 1e-3
    assert lrs[500] == pytest.approx(0.5e-3)
    assert all(a > b for a, b in itertools.pairwise(lrs))
    assert 0.0 < lrs[-1] < 1e-8  # the last batch still learns, barely
    for step in (-1, 1000):
        with pytest.raises(ValueError, match="outside"):
            cosine_lr(1e-3, step, 1000)


def test_a_cosine_run_sets_each_batchs_lr_on_one_curve_across_epochs(
    smoke_dataset, tmp_path
) -> None:
    # 64 samples in batches of 32: 2 batches an epoch, 4 in the run; each epoch records the lr
    # of its last batch, and the checkpoint's optimizer holds it
    result = train(quick(smoke_dataset, tmp_path, max_epochs=2, lr_schedule="cosine"))
    assert [row["lr"] for row in result.history] == [
        pytest.approx(cosine_lr(5e-3, 1, 4)),
        pytest.approx(cosine_lr(5e-3, 3, 4)),
    ]
    groups = load_checkpoint(tmp_path / LAST_NAME)["optimizer"]["param_groups"]
    assert all(g["lr"] == pytest.approx(cosine_lr(5e-3, 3, 4)) for g in groups)
    # the paper's schedule leaves a two-epoch run at its initial lr
    plateau = train(quick(smoke_dataset, tmp_path / "plateau", max_epochs=2))
    assert [row["lr"] for row in plateau.history] == [5e-3, 5e-3]


def test_loss_is_the_mean_squared_error() -> None:
    pred = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    target = torch.tensor([[1.0, 0.0, 3.0], [0.0, 0.0, 1.0]])
    assert velocity_loss(pred, target).item() == pytest.approx((4.0 + 1.0) / 6.0)


def test_speed_weights_grow_with_the_command_from_one_to_the_cap() -> None:
    target = torch.tensor([[0.3, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -10.0]])
    assert speed_weights(target, 1.0, 4.0).tolist() == pytest.approx([1.0, 2.0, 4.0])
    pred = torch.zeros(3, 3)
    equal = weighted_velocity_loss(pred, target, torch.full((3,), 2.5))
    assert equal.item() == pytest.approx(velocity_loss(pred, target).item())


def test_near_weights_climb_inside_the_radius_to_the_cap() -> None:
    nearest = torch.tensor([3.0, 1.5, 1.25, 1.0, 0.5, 0.0])
    weights = near_weights(nearest, 1.5, 4.0).tolist()
    assert weights == pytest.approx([1.0, 1.0, 1.2**4, 4.0, 4.0, 4.0])


def test_a_sample_takes_the_larger_of_its_speed_and_close_range_weights() -> None:
    target = torch.tensor([[3.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.2, 0.0, 0.0]])
    nearest = torch.tensor([1.0, 1.25, 5.0])
    both = SampleWeighting(cap=4.0, speed_mps=1.0, near_m=1.5).weights(target, nearest)
    assert both.tolist() == pytest.approx([4.0, 1.2**4, 1.0])
    speed_only = SampleWeighting(cap=4.0, speed_mps=1.0).weights(target, torch.zeros(0))
    assert speed_only.tolist() == pytest.approx([3.0, 1.0, 1.0])


def test_the_shortfall_counts_only_a_close_answer_short_along_the_target() -> None:
    target = torch.tensor([[2.0, 0.0, 0.0]] * 4 + [[0.0, 0.0, 0.0]])
    pred = torch.tensor(
        [[1.4, 0.0, 0.0], [2.6, 0.0, 0.0], [2.0, 0.5, 0.0], [1.4, 0.0, 0.0], [0.3, 0.0, 0.0]]
    )
    nearest = torch.tensor([0.8, 0.8, 0.8, 1.5, 0.8])
    # short by 0.6 m/s close by; too long, or off to the side: nothing; short but no neighbour
    # within 1.2 m: nothing; a zero target has no direction to fall short along
    assert shortfall(pred, target, nearest, 1.2).tolist() == pytest.approx(
        [0.36 / 3, 0.0, 0.0, 0.0, 0.0]
    )


def test_the_shortfall_term_moves_an_ambiguous_close_fit_towards_the_stronger_answer() -> None:
    # Two close-range samples the images cannot tell apart, commands 1 and 2 m/s along x: the
    # plain MSE answers their mean 1.5; with the shortfall term at K = 2 the fit minimizes
    # (c - 1)^2 + (c - 2)^2 + 2 (2 - c)^2, at c = 7/4: too strong for one, less short for the other.
    target = torch.tensor([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    nearest = torch.tensor([0.7, 0.7])
    for weighting, expected in (
        (None, 1.5),
        (SampleWeighting(cap=4.0, shortfall_weight=2.0), 1.75),
    ):
        c = torch.zeros(1, 3, requires_grad=True)
        optimizer = torch.optim.SGD([c], lr=0.5)
        for _ in range(400):
            pred = c.expand(2, 3)
            loss = (
                velocity_loss(pred, target)
                if weighting is None
                else weighting.loss(pred, target, nearest)
            )
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        assert c[0, 0].item() == pytest.approx(expected, abs=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize(("field", "value"), [("weight_near_m", 1.5), ("weight_shortfall", 2.0)])
def test_a_run_with_a_close_range_loss_trains_and_records_it(
    smoke_dataset, tmp_path, field, value
) -> None:
    result = train(quick(smoke_dataset, tmp_path / "run", max_epochs=2, **{field: value}))
    assert result.epochs_run == 2
    assert all(np.isfinite(row["train_loss"]) for row in result.history)
    saved = torch.load(tmp_path / "run" / "last.ckpt", weights_only=False)
    assert saved["config"][field] == value


@pytest.mark.parametrize(("field", "value"), [("weight_near_m", 1.5), ("weight_shortfall", 2.0)])
def test_a_close_range_loss_without_distances_names_the_field(tmp_path, field, value) -> None:
    images = np.zeros((4, 64, 384), dtype=np.uint8)
    split = InMemorySplit(images, np.zeros((4, 3), dtype=np.float32), {})
    manifest = {"id": "no-distances", "pixel_mean": 128.0, "pixel_std": 64.0}
    config = quick(tmp_path, tmp_path / "run", max_epochs=1, **{field: value})
    with pytest.raises(ConfigError, match=f"{field}.*nearest_m"):
        train_on(config, manifest, split, split)
    assert not (tmp_path / "run" / "last.ckpt").exists()


def test_weighting_moves_the_fit_towards_the_rare_large_commands() -> None:
    # Three hovering samples and one large command that the images cannot tell apart: the plain
    # MSE fit is their mean (shrunk to 1/4 of the large command); the weighted fit keeps more.
    target = torch.tensor([[0.0, 0.0, 0.0]] * 3 + [[3.0, 0.0, 0.0]])
    for weighting, expected in ((None, 0.75), ((1.0, 4.0), 1.5)):
        c = torch.zeros(1, 3, requires_grad=True)
        optimizer = torch.optim.SGD([c], lr=0.5)
        for _ in range(400):
            pred = c.expand(4, 3)
            if weighting is None:
                loss = velocity_loss(pred, target)
            else:
                loss = weighted_velocity_loss(pred, target, speed_weights(target, *weighting))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        assert c[0, 0].item() == pytest.approx(expected, abs=1e-4)


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"weight_speed_mps": 0.0}, "weight_speed_mps"),
        ({"weight_cap": 0.5}, "weight_cap"),
        ({"weight_near_m": 0.0}, "weight_near_m"),
        ({"weight_near_m": float("nan")}, "weight_near_m"),
        ({"weight_shortfall": 0.0}, "weight_shortfall"),
        ({"shortfall_within_m": -1.0}, "shortfall_within_m"),
        ({"lr_schedule": "linear"}, "lr_schedule"),
        ({"batch_size": 0}, "batch_size"),
        ({"lr": -1.0}, "lr"),
        ({"device": "tpu"}, "device"),
        ({"momentum": 1.0}, "momentum"),
        ({"limit_train": 0}, "limit_train"),
        ({"grad_clip_norm": 0.0}, "grad_clip_norm"),
        ({"dropout": 1.0}, "dropout"),
    ],
)
def test_bad_settings_name_the_field(tmp_path, overrides, field) -> None:
    with pytest.raises(ConfigError, match=field):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, **overrides)


class _TwoParams(torch.nn.Module):
    """Same parameter names, registration order chosen by the caller."""

    def __init__(self, order: tuple[str, str]) -> None:
        super().__init__()
        shapes = {"head": (3,), "norm": (8,)}
        for name in order:
            self.register_parameter(name, torch.nn.Parameter(torch.zeros(shapes[name])))


def _stepped_sgd(model: torch.nn.Module) -> torch.optim.SGD:
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1, momentum=0.9)
    for param in model.parameters():
        param.grad = torch.arange(param.numel(), dtype=torch.float32) + param.numel()
    optimizer.step()
    return optimizer


def test_resume_maps_optimizer_state_by_parameter_name_not_position() -> None:
    before = _TwoParams(("head", "norm"))
    saved = optimizer_state(_stepped_sgd(before), before)
    after = _TwoParams(("norm", "head"))  # a refactor reordered the attributes
    optimizer = torch.optim.SGD(after.parameters(), lr=0.1, momentum=0.9)

    load_optimizer_state(optimizer, after, saved)

    for name, param in after.named_parameters():
        buffer = optimizer.state[param]["momentum_buffer"]
        assert buffer.shape == param.shape, name
        assert torch.equal(buffer, torch.arange(param.numel(), dtype=torch.float32) + param.numel())


def test_resume_refuses_optimizer_state_that_does_not_fit_naming_the_parameter() -> None:
    before = _TwoParams(("head", "norm"))
    saved = optimizer_state(_stepped_sgd(before), before)
    del saved["param_names"]  # positions only, as torch stores it
    after = _TwoParams(("norm", "head"))
    optimizer = torch.optim.SGD(after.parameters(), lr=0.1, momentum=0.9)
    with pytest.raises(CheckpointError, match="momentum_buffer for norm has shape"):
        load_optimizer_state(optimizer, after, saved)
