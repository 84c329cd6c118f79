"""The dataset: paper-exact targets and termination rules, store, splits, resume, merge."""

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.flocking import FlockingParams
from sim_harness.dataset.generate import generate, merge
from sim_harness.dataset.runs import initial_conditions, simulate_run, termination
from sim_harness.dataset.spec import SPLITS, DatasetSpec, sample_in_cone
from sim_harness.dataset.store import open_dataset, run_path
from sim_harness.errors import ConfigError, DatasetError
from sim_harness.sim.render import PyBulletRenderer
from sim_harness.sim.world import World


def rotmat_from_wxyz(q):
    """Written out independently of companion.frames."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def reynolds_by_hand(pos, i, params):
    sep, coh, count = np.zeros(3), np.zeros(3), 0
    for j in range(len(pos)):
        r = pos[j] - pos[i]
        d = np.linalg.norm(r)
        if j == i or d >= params.r_max_m:
            continue
        count += 1
        sep += r / d**2
        coh += r
    return (-params.k_sep * sep + params.k_coh * coh) / max(count, 1)


def test_stored_targets_are_the_world_reynolds_command_rotated_into_the_body(smoke_dataset):
    split = open_dataset(smoke_dataset).split("train")
    meta, targets = split.meta, split.targets
    params = FlockingParams()
    checked = 0
    for run in np.unique(meta["run"]):
        rows = np.flatnonzero(meta["run"] == run)
        for t in np.unique(meta["time_s"][rows])[::5]:
            at = rows[meta["time_s"][rows] == t]
            pos = meta["pos_world_enu"][at].astype(np.float64)
            for k, row in enumerate(at):
                v_world = reynolds_by_hand(pos, k, params)
                v_body = rotmat_from_wxyz(meta["q_world_body"][row].astype(np.float64)).T @ v_world
                np.testing.assert_allclose(targets[row], v_body, atol=2e-3)
                np.testing.assert_allclose(meta["rey_world_enu"][row], v_world, atol=2e-3)
                checked += 1
    assert checked >= 30


def test_rotating_the_scene_about_the_vertical_leaves_body_targets_unchanged(smoke_spec):
    spec = DatasetSpec.from_dict({**smoke_spec.as_dict(), "max_run_s": 1.5})
    pos, vel, mig = initial_conditions(spec, "train", 3)
    centre = np.array(spec.spawn_center_m)
    angle = math.radians(73.0)
    rz = np.array(
        [[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]]
    )
    rotated = ((pos - centre) @ rz.T + centre, vel @ rz.T, (mig - centre) @ rz.T + centre)
    renderer = PyBulletRenderer()
    with World(spec.n_agents) as world:
        a = simulate_run(spec, "train", 3, world, renderer, (pos, vel, mig))
        b = simulate_run(spec, "train", 3, world, renderer, rotated)
    assert a.n_samples == b.n_samples > 0
    np.testing.assert_allclose(a.arrays["targets"], b.arrays["targets"], atol=1e-4)
    # ...while the world-frame commands did rotate.
    np.testing.assert_allclose(
        b.arrays["rey_world_enu"], a.arrays["rey_world_enu"] @ rz.T.astype(np.float32), atol=1e-4
    )
    assert np.abs(a.arrays["rey_world_enu"] - b.arrays["rey_world_enu"]).max() > 0.05


@pytest.mark.parametrize(
    ("positions", "t_s", "expected"),
    [
        ([[0, 0, 5], [2, 0, 5], [29.5, 0, 5]], 0.0, "arrival"),  # within 1 m of (30, 0, 5)
        ([[0, 0, 5], [0.9, 0, 5], [0, 2, 5]], 0.0, "collision"),
        ([[0, 0, 5], [3, 0, 5], [-4.1, 0, 5]], 0.0, "dispersion"),  # 7.1 m apart
        ([[0, 0, 5], [2, 0, 5], [0, 2, 0.4]], 0.0, "ground"),
        ([[0, 0, 5], [2, 0, 5], [0, 2, 5]], 60.0, "time_limit"),
        ([[0, 0, 5], [2, 0, 5], [0, 2, 5]], 10.0, None),
    ],
)
def test_each_termination_rule(positions, t_s, expected) -> None:
    spec = DatasetSpec(n_agents=3)
    assert termination(spec, np.array(positions, float), np.array([30.0, 0, 5]), t_s) == expected


def test_velocity_commands_lie_uniformly_inside_the_unit_cone() -> None:
    axis = np.array([0.0, 1.0, 0.0])
    v = sample_in_cone(np.random.default_rng(0), 20_000, axis, math.radians(15), 1.0)
    along = v @ axis
    angle = np.degrees(np.arccos(np.clip(along / np.linalg.norm(v, axis=1), -1, 1)))
    assert angle.max() <= 15.0 + 1e-9 and along.max() <= 1.0
    # Uniform in volume: P(height < h) = h^3, so the median height is 0.5^(1/3) = 0.794.
    assert np.median(along) == pytest.approx(0.5 ** (1 / 3), abs=0.01)


def test_a_run_flies_through_the_vehicle_model_with_realistic_attitudes(smoke_dataset):
    meta = open_dataset(smoke_dataset).split("train").meta
    q = meta["q_world_body"].astype(np.float64)
    tilt = np.degrees(np.arccos(np.clip(1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2), -1, 1)))
    assert tilt.max() > 2.0  # accelerating from rest tilts the cameras
    assert tilt.max() < 45.0  # PX4's tilt limit
    speed = np.linalg.norm(meta["vel_world_enu"], axis=1)
    assert speed[meta["time_s"] == 0].max() == 0.0  # runs start at rest
    assert speed.max() > 0.3


def test_store_reads_splits_as_arrays_and_memory_maps_the_images(smoke_dataset, smoke_spec):
    ds = open_dataset(smoke_dataset)
    m = ds.manifest
    for split in SPLITS:
        data = ds.split(split)
        assert data.n_samples == m["counts"][split] >= smoke_spec.target(split)
        assert data.images.shape == (data.n_samples, 64, 384)
        assert data.images.dtype == np.uint8 and isinstance(data.images, np.memmap)
        assert data.targets.shape == (data.n_samples, 3) and data.targets.dtype == np.float32
        for key in ("run", "agent", "time_s", "n_neighbours", "nearest_m", "pos_world_enu"):
            assert len(data.meta[key]) == data.n_samples
    train = ds.split("train").images
    assert m["pixel_mean"] == pytest.approx(float(train.mean()), abs=1e-6)
    assert m["pixel_std"] == pytest.approx(float(train.std()), abs=1e-4)
    for key in ("camera", "frames", "code_version", "spec", "scene", "command", "target_stats"):
        assert key in m


def test_uncompressed_runs_hold_the_same_samples_and_read_the_same(
    smoke_dataset, smoke_spec, tmp_path
) -> None:
    """`--compression none`: stored zip members (twice the disk, no deflate): the same dataset."""
    import dataclasses
    import zipfile

    spec = dataclasses.replace(smoke_spec, compression="none")
    stored = generate(tmp_path / "stored", spec, workers=1, progress=False)
    deflated = open_dataset(smoke_dataset)
    assert stored.manifest["id"] == deflated.manifest["id"]  # the same samples
    assert stored.manifest["counts"] == deflated.manifest["counts"]
    for split in SPLITS:
        a, b = stored.split(split), deflated.split(split)
        np.testing.assert_array_equal(a.images, b.images)
        np.testing.assert_array_equal(a.targets, b.targets)
    first = run_path(stored.root, "train", 0)
    with zipfile.ZipFile(first) as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
    assert first.stat().st_size > 1.5 * run_path(deflated.root, "train", 0).stat().st_size
    with pytest.raises(ConfigError, match="dataset.compression: 'lz4' must be one of deflate"):
        dataclasses.replace(smoke_spec, compression="lz4")


def test_splits_are_disjoint_by_run(smoke_dataset):
    ds = open_dataset(smoke_dataset)
    starts = {}
    for split in SPLITS:
        meta = ds.split(split).meta
        for run in np.unique(meta["run"]):
            first = meta["pos_world_enu"][(meta["run"] == run) & (meta["time_s"] == 0)]
            starts[(split, int(run))] = first.tobytes()
    assert len(set(starts.values())) == len(starts)  # no run appears twice, in any split


def _dataset_arrays(root: Path) -> dict[str, np.ndarray]:
    ds = open_dataset(root)
    out = {}
    for split in SPLITS:
        data = ds.split(split)
        out[f"{split}/images"] = np.asarray(data.images)
        out[f"{split}/targets"] = data.targets
        for key, value in data.meta.items():
            out[f"{split}/{key}"] = value
    return out


def _without_run_details(manifest: dict) -> dict:
    return {k: v for k, v in manifest.items() if k not in ("generation", "command", "code_version")}


def test_killed_generation_resumes_to_exactly_the_uninterrupted_dataset(
    smoke_dataset, tmp_path
) -> None:
    out = tmp_path / "resumed"
    cmd = [
        sys.executable, "-m", "sim_harness.cli", "dataset", "generate", "--preset", "smoke",
        "--out", str(out), "--workers", "2", "--no-progress",
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, start_new_session=True, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list((out / "runs").glob("*/*.npz")):
        assert proc.poll() is None, "generation ended before it could be interrupted"
        assert time.monotonic() < deadline
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole process group: main process and workers
    proc.wait()
    assert not (out / "manifest.json").exists()
    with pytest.raises(DatasetError, match="not finished"):
        open_dataset(out)
    subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
    assert _without_run_details(json.loads((out / "manifest.json").read_text())) == (
        _without_run_details(json.loads((smoke_dataset / "manifest.json").read_text()))
    )
    resumed, reference = _dataset_arrays(out), _dataset_arrays(smoke_dataset)
    assert resumed.keys() == reference.keys()
    for key in reference:
        np.testing.assert_array_equal(resumed[key], reference[key], err_msg=key)


def test_resume_with_other_parameters_is_refused(tmp_path, smoke_spec) -> None:
    tiny = DatasetSpec.from_dict(
        {**smoke_spec.as_dict(), "train_samples": 30, "val_samples": 30, "test_samples": 30,
         "max_run_s": 0.5}
    )  # fmt: skip
    generate(tmp_path, tiny, workers=1, progress=False)
    other = DatasetSpec.from_dict({**tiny.as_dict(), "cone_half_angle_deg": 30.0})
    with pytest.raises(DatasetError, match="cone_half_angle_deg"):
        generate(tmp_path, other, workers=1, progress=False)


def test_shards_merge_into_one_dataset_without_duplicates(tmp_path, smoke_spec) -> None:
    base = {**smoke_spec.as_dict(), "train_samples": 50, "val_samples": 20, "test_samples": 20,
            "max_run_s": 0.5}  # fmt: skip
    shards = []
    for index in range(2):
        spec = DatasetSpec.from_dict({**base, "shard_index": index, "shard_count": 2})
        shards.append(generate(tmp_path / f"shard{index}", spec, workers=1, progress=False))
    merged = merge([s.root for s in shards] + [shards[0].root], tmp_path / "merged")
    for split in SPLITS:
        runs = [set(s.split(split).runs) for s in shards]
        assert not runs[0] & runs[1]  # shards interleave run indices
        assert set(merged.split(split).runs) == runs[0] | runs[1]
        assert merged.manifest["counts"][split] == sum(s.manifest["counts"][split] for s in shards)
        for k in merged.split(split).runs:
            assert run_path(merged.root, split, k).exists()
    other = DatasetSpec.from_dict({**base, "seed": 1})
    third = generate(tmp_path / "other", other, workers=1, progress=False)
    with pytest.raises(DatasetError, match="different parameters"):
        merge([shards[0].root, third.root], tmp_path / "bad")


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("n_agents", 1, "dataset.n_agents"),
        ("cone_half_angle_deg", 120.0, "dataset.cone_half_angle_deg"),
        ("train_samples", 0, "dataset.train_samples"),
        ("dispersion_m", 0.5, "dataset.dispersion_m"),
        ("shard_index", 3, "dataset.shard_index"),
    ],
)
def test_invalid_parameters_name_the_field(field, value, match) -> None:
    with pytest.raises(ConfigError, match=match):
        DatasetSpec.from_dict(
            {field: value, **({"shard_count": 2} if field == "shard_index" else {})}
        )


def test_inspect_prints_counts_and_writes_figures(smoke_dataset, tmp_path, capsys) -> None:
    from sim_harness.cli import main

    assert main(["dataset", "inspect", str(smoke_dataset), "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "train" in text and "dispersion" in text and "pixel mean" in text
    assert (tmp_path / "targets_hist.png").stat().st_size > 10_000
    assert (tmp_path / "samples.png").stat().st_size > 10_000


def test_inspect_writes_nothing_into_the_dataset(smoke_dataset, tmp_path, monkeypatch) -> None:
    from sim_harness.cli import main

    def files() -> list[Path]:
        return sorted(p.relative_to(smoke_dataset) for p in smoke_dataset.rglob("*"))

    before = files()
    monkeypatch.chdir(tmp_path)
    assert main(["dataset", "inspect", str(smoke_dataset)]) == 0
    assert files() == before  # no image cache, no figures
    out = tmp_path / "runs" / "inspect" / smoke_dataset.name  # the default
    assert (out / "samples.png").stat().st_size > 10_000
    assert main(["dataset", "inspect", str(smoke_dataset), "--out", str(smoke_dataset / "f")]) == 2
    assert files() == before


def test_the_progress_bar_ends_on_the_samples_written_past_the_target(
    smoke_dataset, smoke_spec, tmp_path, capsys
) -> None:
    # The runs of the smoke dataset but the last of each split: generation makes those again.
    root = tmp_path / "resumed"
    (root / "runs").mkdir(parents=True)
    (root / "spec.json").write_bytes((smoke_dataset / "spec.json").read_bytes())
    manifest = json.loads((smoke_dataset / "manifest.json").read_text())
    for split in SPLITS:
        (root / "runs" / split).mkdir()
        for entry in manifest["splits"][split]["runs"][:-1]:
            src = run_path(smoke_dataset, split, entry["run_index"])
            os.link(src, run_path(root, split, entry["run_index"]))
    dataset = generate(root, smoke_spec, workers=1, progress=True, command="pytest")
    err = capsys.readouterr().err  # not a terminal: plain lines
    for split in SPLITS:
        written = dataset.manifest["counts"][split]
        assert written > smoke_spec.target(split)  # a split ends with a whole run
        last = [line for line in err.splitlines() if line.startswith(f"{split:5s}:")][-1]
        assert f" 100% {written}/{written} " in last, last
