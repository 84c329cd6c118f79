"""The flock-sum loss term: flocks found in the data, batched whole, errors summed in the world."""

import numpy as np
import pytest
import torch

from companion.errors import ConfigError
from companion.frames import quat_from_yaw
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.batches import InMemorySplit, epoch_rows, with_repeats
from sim_harness.learning.flock_loss import (
    flock_batches,
    flock_ids,
    flock_term,
    world_rotations,
)
from sim_harness.learning.symmetry import augment_with_views
from sim_harness.learning.train import TrainConfig, train


def test_a_flock_is_one_run_at_one_time_step_of_one_part() -> None:
    meta = {
        "run": np.array([0, 0, 0, 0, 1, 1, 0, 0]),
        "time_s": np.array([0.1, 0.1, 0.2, 0.2, 0.1, 0.1, 0.1, 0.1], dtype=np.float32),
        "q_world_body": np.zeros((8, 4)),
        "part": np.array([0, 0, 0, 0, 0, 0, 1, 1]),
    }
    assert flock_ids(meta).tolist() == [0, 0, 1, 1, 2, 2, 3, 3]


def test_data_without_the_flock_columns_is_refused_naming_them() -> None:
    with pytest.raises(ConfigError, match="weight_flock.*q_world_body"):
        flock_ids({"run": np.zeros(3), "time_s": np.zeros(3)})


def test_the_rotations_turn_each_teacher_label_into_its_world_command(smoke_dataset) -> None:
    split = open_dataset(smoke_dataset).split("train")
    world = np.einsum("nij,nj->ni", world_rotations(split.meta), split.targets)
    np.testing.assert_allclose(world, split.meta["rey_world_enu"], atol=1e-5)


def test_batches_hold_whole_flocks_each_showing_once_seeded() -> None:
    # 10 flocks of 3 (flocks 6-9 shown twice per epoch), batches of at most 7 samples
    n = 30
    flock_id = np.repeat(np.arange(10), 3)
    counts = np.where(flock_id >= 6, 2, 1).astype(np.int64)
    split = with_repeats(
        InMemorySplit(np.zeros((n, 1, 1), np.uint8), np.zeros((n, 3), np.float32), {}), counts
    )
    rows = epoch_rows(split)
    batches = flock_batches(flock_id, rows, 7, seed=3, epoch=1)
    assert all(len(b_rows) <= 7 for b_rows, _ in batches)
    shown = np.concatenate([b_rows for b_rows, _ in batches])
    assert np.array_equal(np.bincount(shown, minlength=n), counts)
    showings = 0
    for b_rows, local in batches:
        assert np.array_equal(b_rows, np.sort(b_rows))
        for k in np.unique(local):
            members = b_rows[local == k]
            assert len(set(flock_id[members].tolist())) == 1  # one flock per local index
            assert (
                sorted(members.tolist())
                == np.flatnonzero(flock_id == flock_id[members[0]]).tolist()
            )
            showings += 1
    assert showings == 14  # 6 flocks once, 4 flocks twice
    again = flock_batches(flock_id, rows, 7, seed=3, epoch=1)
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(batches, again, strict=True))
    other = flock_batches(flock_id, rows, 7, seed=3, epoch=2)
    assert any(not np.array_equal(a[0], b[0]) for a, b in zip(batches, other, strict=False))


def test_a_shared_world_error_costs_n_times_an_independent_one() -> None:
    eye = torch.eye(3).expand(4, 3, 3)
    one_flock = torch.zeros(4, dtype=torch.int64)
    shared = torch.tensor([[0.1, 0.0, 0.0]] * 4)
    independent = torch.tensor([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.1, 0], [0, -0.1, 0]])
    mse = 0.01 / 3
    assert flock_term(shared, eye, one_flock, 1).item() == pytest.approx(4 * mse)
    assert flock_term(independent, eye, one_flock, 1).item() == pytest.approx(0.0, abs=1e-9)
    # each drone its own flock: the term is the mean squared error
    alone = torch.arange(4)
    assert flock_term(shared, eye, alone, 4).item() == pytest.approx(mse)


def test_errors_are_summed_in_the_world_not_the_body_frame() -> None:
    # two drones facing opposite ways, each 0.1 m/s too slow forward in its own body frame:
    # in the world the errors cancel; the same body error with both facing east adds up
    body_error = torch.tensor([[-0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]])
    pair = torch.zeros(2, dtype=torch.int64)
    facing = {"q_world_body": quat_from_yaw(np.array([0.0, np.pi]))}
    opposite = torch.from_numpy(world_rotations(facing))
    assert flock_term(body_error, opposite, pair, 1).item() == pytest.approx(0.0, abs=1e-9)
    same = torch.eye(3).expand(2, 3, 3)
    assert flock_term(body_error, same, pair, 1).item() == pytest.approx(0.04 / 6)


def test_an_augmented_error_turned_back_by_its_view_matrix_is_the_recorded_one() -> None:
    generator = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (16, 64, 384), dtype=torch.uint8)
    targets = torch.randn(16, 3)
    _, labels, views = augment_with_views(images, targets, generator, "d4")
    back = torch.bmm(views.transpose(1, 2), labels.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(back, targets)


@pytest.mark.slow
def test_a_run_with_the_flock_term_trains_and_records_it(smoke_dataset, tmp_path) -> None:
    config = TrainConfig(
        dataset=smoke_dataset,
        out_dir=tmp_path / "run",
        max_epochs=2,
        batch_size=32,
        lr=1e-3,
        augment="d4",
        weight_flock=1.0,
        progress=False,
    )
    result = train(config)
    assert result.epochs_run == 2
    assert all(np.isfinite(row["train_loss"]) for row in result.history)
    assert result.best_val_loss < result.initial_val_loss
    saved = torch.load(tmp_path / "run" / "last.ckpt", weights_only=False)
    assert saved["config"]["weight_flock"] == 1.0


def test_a_bad_flock_weight_names_the_field(tmp_path) -> None:
    with pytest.raises(ConfigError, match="weight_flock"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, weight_flock=0.0)
