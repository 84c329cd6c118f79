"""Close encounters drawn from a dataset's flocks: one pair brought close, every label exact."""

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.flocking import FlockingParams
from companion.frames import quat_to_rotmat
from sim_harness.dataset.close_range import (
    CORNER_FACENESS,
    CloseRangeDraw,
    close_range,
    move_nearest_closer,
)
from sim_harness.dataset.rerender import rerender
from sim_harness.dataset.runs import teacher_targets
from sim_harness.dataset.store import open_dataset, run_path, stored_runs
from sim_harness.errors import DatasetError


def _steps(z, n_agents):
    """(time_s, pos, q, targets, nearest, images) of a run file, one row per step."""
    n = len(z["agent"]) // n_agents
    return (
        z["time_s"].reshape(n, n_agents)[:, 0],
        z["pos_world_enu"].reshape(n, n_agents, 3).astype(np.float64),
        z["q_world_body"].reshape(n, n_agents, 4).astype(np.float64),
        z["targets"].reshape(n, n_agents, 3),
        z["nearest_m"].reshape(n, n_agents),
        z["images"].reshape(n, n_agents, 64, 384),
    )


def test_each_step_gets_one_pair_in_range_the_flock_redrawn_and_labelled_exactly(
    smoke_dataset, tmp_path
) -> None:
    source = open_dataset(smoke_dataset)
    n_agents = source.manifest["spec"]["n_agents"]
    flocking = FlockingParams(**source.manifest["spec"]["flocking"])
    out = close_range(
        smoke_dataset,
        tmp_path / "close",
        CloseRangeDraw(steps_per_run=4, min_m=0.5, max_m=0.8, seed=1),
        workers=1,
        progress=False,
    )
    assert out.manifest["close_range"] == {
        "steps_per_run": 4,
        "min_m": 0.5,
        "max_m": 0.8,
        "seed": 1,
        "bearing": "kept",
    }
    assert out.manifest["close_range_from"]["id"] == source.id
    assert set(out.manifest["counts"]) == {"train", "val", "test"}
    checked = 0
    for split in ("train", "val", "test"):
        assert sorted(stored_runs(tmp_path / "close", split)) == sorted(
            stored_runs(smoke_dataset, split)
        )
        for k in stored_runs(tmp_path / "close", split):
            with np.load(run_path(smoke_dataset, split, k)) as z:
                s_time, s_pos, s_q, _, s_near, s_img = _steps(z, n_agents)
            with np.load(run_path(tmp_path / "close", split, k)) as z:
                time_s, pos, q, targets, nearest, images = _steps(z, n_agents)
            assert 1 <= len(time_s) <= 4
            assert len(set(time_s.tolist())) == len(time_s)  # distinct steps
            for t, p, qq, tgt, near, img in zip(
                time_s, pos, q, targets, nearest, images, strict=True
            ):
                src = int(np.flatnonzero(s_time == t)[0])
                moved = np.flatnonzero(np.linalg.norm(p - s_pos[src], axis=1) > 1e-4)
                assert len(moved) == 1  # one drone moved, the rest of the flock where it was
                np.testing.assert_array_equal(qq, s_q[src])  # attitudes kept
                j = int(moved[0])
                d = np.linalg.norm(p - p[j], axis=1)
                d[j] = np.inf
                assert 0.5 - 1e-4 <= d.min() <= 0.8 + 1e-4  # its new nearest is in range
                assert near[j] < s_near[src].min()  # closer than the flight ever held here
                label = teacher_targets(p, qq, flocking)  # the teacher at the new positions
                np.testing.assert_allclose(tgt, label["rey_body"], atol=1e-4)
                np.testing.assert_allclose(near, label["nearest_m"], atol=1e-4)
                assert (img[j] != s_img[src][j]).any()  # drawn again
                checked += 1
    assert checked >= 6


def test_the_same_seed_draws_the_same_bytes_and_an_interrupted_draw_resumes(
    smoke_dataset, tmp_path
) -> None:
    root = tmp_path / "close"
    first = close_range(smoke_dataset, root, CloseRangeDraw(3, seed=4), workers=1, progress=False)
    run = min(stored_runs(root, "train"))
    path = run_path(root, "train", run)
    kept = path.read_bytes()
    path.unlink()
    path.with_name(path.name + ".tmp").write_bytes(b"partial")
    again = close_range(smoke_dataset, root, CloseRangeDraw(3, seed=4), workers=1, progress=False)
    assert path.read_bytes() == kept
    assert not list(root.glob("runs/*/*.tmp"))
    assert again.id == first.id
    other = close_range(
        smoke_dataset, tmp_path / "other", CloseRangeDraw(3, seed=5), workers=1, progress=False
    )
    assert other.id != first.id


def test_a_third_drone_never_ends_closer_than_the_range(tmp_path) -> None:
    # i = 0 with j = 1 at 2 m; a third drone sits 0.3 m beside j's new place: no try may keep it
    pos = np.array([[0.0, 0.0, 5.0], [2.0, 0.0, 5.0], [0.6, 0.3, 5.0]])
    rng = np.random.default_rng(0)
    for _ in range(50):
        result = move_nearest_closer(pos, rng, 0.4, 1.1)
        if result is None:
            continue
        moved, i, j = result
        d = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        assert 0.4 - 1e-9 <= d[i, j] <= 1.1 + 1e-9
        assert np.delete(d[j], [i, j]).min() >= 0.4


def test_a_corner_bearing_puts_the_neighbour_where_three_faces_meet() -> None:
    rng = np.random.default_rng(3)
    pos = rng.uniform(-3, 3, size=(9, 3))
    # agent attitudes: random yaws (a body frame turned about z)
    yaw = rng.uniform(-np.pi, np.pi, size=9)
    q = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=1)
    found = 0
    for _ in range(40):
        result = move_nearest_closer(pos, rng, 0.4, 1.1, q)
        if result is None:
            continue
        moved, i, j = result
        offset = moved[j] - moved[i]
        body = quat_to_rotmat(q[i]).T @ offset
        assert 0.4 - 1e-9 <= np.linalg.norm(body) <= 1.1 + 1e-9
        faceness = np.abs(body).max() / np.linalg.norm(body)
        assert faceness < CORNER_FACENESS  # off every face's centre: towards a corner
        found += 1
    assert found >= 10
    with pytest.raises(ConfigError, match="close-range.bearing"):
        CloseRangeDraw(bearing="random")


def test_bad_ranges_and_sources_are_refused_naming_the_field(smoke_dataset, tmp_path) -> None:
    with pytest.raises(ConfigError, match="close-range.max_m"):
        CloseRangeDraw(min_m=0.9, max_m=0.6)
    with pytest.raises(ConfigError, match="close-range.min_m"):
        CloseRangeDraw(min_m=0.0)
    with pytest.raises(ConfigError, match="close-range.steps_per_run"):
        CloseRangeDraw(steps_per_run=0)
    with pytest.raises(DatasetError, match="another folder"):
        close_range(smoke_dataset, smoke_dataset, progress=False)
    varied = rerender(
        smoke_dataset, tmp_path / "varied", "raycast-aa", workers=1, progress=False, vary_scene=2
    )
    with pytest.raises(DatasetError, match="varied scenes"):
        close_range(varied.root, tmp_path / "y", progress=False)
