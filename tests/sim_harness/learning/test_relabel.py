"""A more cautious teacher's labels, recomputed from each flock's stored positions."""

import numpy as np
import pytest
import torch

from companion.errors import ConfigError
from companion.flocking import FlockingParams, flocking_command
from companion.frames import quat_to_rotmat
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.relabel import cautious_targets
from sim_harness.learning.train import TrainConfig, train


def _flocks(sizes: tuple[int, ...], seed: int = 5) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Stored-like labels (the law's Reynolds command, body frame) and meta of several flocks."""
    rng = np.random.default_rng(seed)
    labels, pos_all, q_all, run, time = [], [], [], [], []
    for k, n in enumerate(sizes):
        pos = rng.uniform(-3.0, 3.0, size=(n, 3))
        pos[1] = pos[0] + [0.6, 0.2, 0.0]  # a close pair: the separation term matters
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        rey = flocking_command(pos, None, FlockingParams()).reynolds
        labels.append(np.einsum("nji,nj->ni", quat_to_rotmat(q), rey))
        pos_all.append(pos)
        q_all.append(q)
        run += [k // 2] * n  # two time steps per run
        time += [0.1 * (k % 2)] * n
    meta = {
        "pos_world_enu": np.concatenate(pos_all).astype(np.float32),
        "q_world_body": np.concatenate(q_all).astype(np.float32),
        "run": np.array(run),
        "time_s": np.array(time, dtype=np.float32),
    }
    return np.concatenate(labels).astype(np.float32), meta


def test_the_labels_are_the_law_with_the_scaled_separation_gain() -> None:
    labels, meta = _flocks((9, 3, 12, 9))
    np.testing.assert_allclose(cautious_targets(labels, meta, 1.0), labels, atol=1e-6)
    scaled = cautious_targets(labels, meta, 1.25)
    pos = meta["pos_world_enu"].astype(np.float64)
    rot = quat_to_rotmat(meta["q_world_body"].astype(np.float64))
    params = FlockingParams(k_sep=FlockingParams().k_sep * 1.25)
    start = 0
    for n in (9, 3, 12, 9):
        rows = slice(start, start + n)
        rey = flocking_command(pos[rows], None, params).reynolds
        expected = np.einsum("nji,nj->ni", rot[rows], rey)
        np.testing.assert_allclose(scaled[rows], expected, atol=1e-4)
        start += n
    # the close pair now flees each other harder
    away = pos[0] - pos[1]
    world0 = rot[0] @ scaled[0]
    assert world0 @ away > (rot[0] @ labels[0]) @ away + 0.1


def test_an_incomplete_flock_is_refused_naming_the_sample() -> None:
    labels, meta = _flocks((9, 9))
    keep = np.arange(len(labels)) != 4  # one drone of the first flock missing
    cut = {k: v[keep] for k, v in meta.items()}
    with pytest.raises(ConfigError, match=r"separation_scale: the data's labels .*run 0"):
        cautious_targets(labels[keep], cut, 1.2, what="the data")


def test_data_without_positions_is_refused_naming_the_column() -> None:
    labels, meta = _flocks((3,))
    del meta["pos_world_enu"]
    with pytest.raises(ConfigError, match="pos_world_enu"):
        cautious_targets(labels, meta, 1.2)


def test_a_scale_out_of_range_names_the_field(tmp_path) -> None:
    with pytest.raises(ConfigError, match="separation_scale"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, separation_scale=3.0)


@pytest.mark.slow
def test_a_run_learns_and_validates_on_the_cautious_labels(smoke_dataset, tmp_path) -> None:
    config = TrainConfig(
        dataset=smoke_dataset,
        out_dir=tmp_path / "run",
        max_epochs=1,
        batch_size=32,
        lr=1e-3,
        separation_scale=1.3,
        progress=False,
    )
    result = train(config)
    # the untrained network answers zero (its head starts at zero), so its validation loss is
    # the mean square of the labels it is judged on: the cautious ones
    val = open_dataset(smoke_dataset).split("val")
    cautious = cautious_targets(val.targets, val.meta, 1.3)
    assert result.initial_val_loss == pytest.approx(float(np.mean(cautious**2)), rel=1e-4)
    recorded = float(np.mean(np.square(val.targets)))
    assert abs(float(np.mean(cautious**2)) - recorded) > 0.01 * recorded  # not the recorded ones
    saved = torch.load(tmp_path / "run" / "last.ckpt", weights_only=False)
    assert saved["config"]["separation_scale"] == 1.3


def _boosted_law_body(
    pos: np.ndarray,
    rot: np.ndarray,
    scale: float,
    near: float,
    radius: float = 1.2,
    ramp: float = 0.0,
    reach: float = np.inf,
) -> np.ndarray:
    """Agent by agent, the separation sum with neighbours within `radius` weighing `near` (the
    weight rising linearly from 1 at `radius` to `near` at `radius` - `ramp`), those within
    `reach` x `scale`, plus cohesion, in each agent's body frame: an independent statement of
    the law."""
    p = FlockingParams()
    out = np.zeros_like(pos)
    for i in range(len(pos)):
        r = np.delete(pos - pos[i], i, axis=0)
        d = np.linalg.norm(r, axis=1)
        if ramp > 0:
            w = 1.0 + (near - 1.0) * np.clip((radius - d) / ramp, 0.0, 1.0)
        else:
            w = np.where(d < radius, near, 1.0)
        w = w * np.where(d < reach, scale, 1.0)
        sep = -p.k_sep / len(r) * (w[:, None] * r / d[:, None] ** 2).sum(axis=0)
        coh = p.k_coh / len(r) * r.sum(axis=0)
        out[i] = rot[i].T @ (sep + coh)
    return out


def _assert_is_boosted_law(
    got: np.ndarray, pos: np.ndarray, rot: np.ndarray, scale: float, near: float, **law: float
) -> None:
    """`got`, flock by flock (the sizes 9, 3, 12, 9 of the tests' `_flocks`), is the law's."""
    start = 0
    for n in (9, 3, 12, 9):
        rows = slice(start, start + n)
        expected = _boosted_law_body(pos[rows], rot[rows], scale, near, **law)
        np.testing.assert_allclose(got[rows], expected, atol=1e-4)
        start += n


def test_the_close_range_boost_weighs_the_near_neighbours_only() -> None:
    labels, meta = _flocks((9, 3, 12, 9))
    pos = meta["pos_world_enu"].astype(np.float64)
    rot = quat_to_rotmat(meta["q_world_body"].astype(np.float64))
    boosted = cautious_targets(labels, meta, 1.1, near_scale=2.0)
    _assert_is_boosted_law(boosted, pos, rot, 1.1, 2.0)
    # agents with no neighbour within 1.2 m get the k_sep x 1.1 labels unchanged by the boost
    d = np.linalg.norm(pos[:9, None] - pos[None, :9], axis=-1) + 10 * np.eye(9)
    alone = np.flatnonzero(d.min(axis=1) >= 1.2)
    assert len(alone) > 0
    plain = cautious_targets(labels, meta, 1.1)
    np.testing.assert_allclose(boosted[alone], plain[alone], atol=1e-6)
    # the close pair (agents 0 and 1, 0.63 m apart) flees harder than under k_sep x 1.1
    away = pos[0] - pos[1]
    assert (rot[0] @ boosted[0]) @ away > (rot[0] @ plain[0]) @ away + 0.3


def test_a_close_range_boost_out_of_range_names_the_field(tmp_path) -> None:
    with pytest.raises(ConfigError, match="near_separation_scale"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, near_separation_scale=5.0)


def test_the_close_range_boost_reaches_as_far_as_its_radius() -> None:
    labels, meta = _flocks((9, 3, 12, 9), seed=8)
    pos = meta["pos_world_enu"].astype(np.float64)
    rot = quat_to_rotmat(meta["q_world_body"].astype(np.float64))
    wide = cautious_targets(labels, meta, 1.1, near_scale=2.0, near_m=2.5)
    _assert_is_boosted_law(wide, pos, rot, 1.1, 2.0, radius=2.5)
    # a neighbour between 1.2 m and 2.5 m counts in the wide boost and not in the default one
    d = np.linalg.norm(pos[:9, None] - pos[None, :9], axis=-1) + 10 * np.eye(9)
    between = np.flatnonzero((d.min(axis=1) >= 1.2) & (d.min(axis=1) < 2.5))
    assert len(between) > 0
    narrow = cautious_targets(labels, meta, 1.1, near_scale=2.0)
    assert np.abs(wide[between] - narrow[between]).max() > 0.05


def test_a_close_range_radius_out_of_range_names_the_field(tmp_path) -> None:
    with pytest.raises(ConfigError, match="near_separation_radius_m"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, near_separation_radius_m=0.1)


def test_a_ramped_boost_rises_linearly_inside_its_reach() -> None:
    labels, meta = _flocks((9, 3, 12, 9), seed=8)
    pos = meta["pos_world_enu"].astype(np.float64)
    rot = quat_to_rotmat(meta["q_world_body"].astype(np.float64))
    ramped = cautious_targets(labels, meta, 1.1, near_scale=3.0, near_m=2.0, ramp_m=0.8)
    _assert_is_boosted_law(ramped, pos, rot, 1.1, 3.0, radius=2.0, ramp=0.8)
    # no ramp is the step; a ramp boosts less than the step of the same reach, never more
    step = cautious_targets(labels, meta, 1.1, near_scale=3.0, near_m=2.0)
    np.testing.assert_allclose(
        cautious_targets(labels, meta, 1.1, near_scale=3.0, near_m=2.0, ramp_m=0.0), step
    )
    plain = cautious_targets(labels, meta, 1.1)
    away = pos[0] - pos[1]  # the close pair, 0.63 m apart: inside the ramp's full boost
    flee = [(rot[0] @ lab[0]) @ away for lab in (plain, ramped, step)]
    assert flee[0] + 0.3 < flee[1] <= flee[2] + 1e-6


def test_the_scaled_separation_reaches_only_its_radius() -> None:
    labels, meta = _flocks((9, 3, 12, 9), seed=8)
    pos = meta["pos_world_enu"].astype(np.float64)
    rot = quat_to_rotmat(meta["q_world_body"].astype(np.float64))
    near = cautious_targets(labels, meta, 1.2, near_scale=2.0, near_m=1.2, reach_m=2.5)
    _assert_is_boosted_law(near, pos, rot, 1.2, 2.0, radius=1.2, reach=2.5)
    # the far neighbours' separation is the paper's: nearer the stored labels than the law
    # scaled everywhere, and a reach beyond the flock is that law
    everywhere = cautious_targets(labels, meta, 1.2, near_scale=2.0, near_m=1.2)
    assert np.abs(near - labels).mean() < np.abs(everywhere - labels).mean() - 0.01
    far = cautious_targets(labels, meta, 1.2, near_scale=2.0, near_m=1.2, reach_m=20.0)
    np.testing.assert_allclose(far, everywhere, atol=1e-5)


def test_a_ramp_or_a_separation_reach_out_of_range_names_the_field(tmp_path) -> None:
    with pytest.raises(ConfigError, match="near_separation_ramp_m.*shorter"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, near_separation_ramp_m=1.2)
    with pytest.raises(ConfigError, match="near_separation_ramp_m"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, near_separation_ramp_m=-0.1)
    with pytest.raises(ConfigError, match="separation_radius_m.*at least"):
        TrainConfig(
            dataset=tmp_path,
            out_dir=tmp_path,
            near_separation_radius_m=1.35,
            separation_radius_m=1.0,
        )
    with pytest.raises(ConfigError, match="separation_radius_m"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, separation_radius_m=50.0)
