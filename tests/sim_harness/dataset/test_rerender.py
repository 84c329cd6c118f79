"""Redrawing a dataset with another renderer: same states and labels, new images, resumable."""

import json

import numpy as np
import pytest

from sim_harness.dataset.rerender import rerender
from sim_harness.dataset.store import open_dataset, run_path, stored_runs
from sim_harness.errors import ConfigError, DatasetError


def test_redrawing_with_the_same_renderer_gives_the_same_dataset(smoke_dataset, tmp_path) -> None:
    source = open_dataset(smoke_dataset)
    renderer = source.manifest["renderer"]
    out = rerender(smoke_dataset, tmp_path / "again", renderer, workers=1, progress=False)
    assert out.manifest["counts"] == source.manifest["counts"]
    assert out.manifest["rerendered_from"]["id"] == source.id
    for split in ("train", "val", "test"):
        a, b = source.split(split), out.split(split)
        np.testing.assert_array_equal(a.targets, b.targets)
        for key, values in a.meta.items():
            np.testing.assert_array_equal(values, b.meta[key], err_msg=key)
        differ = (np.asarray(a.images) != np.asarray(b.images)).mean()
        assert differ < 1e-4  # float32 poses: an edge pixel here and there
    assert out.manifest["pixel_mean"] == pytest.approx(source.manifest["pixel_mean"], abs=0.01)


def test_redrawing_area_averaged_keeps_the_labels_and_resumes(smoke_dataset, tmp_path) -> None:
    source = open_dataset(smoke_dataset)
    root = tmp_path / "aa"
    out = rerender(smoke_dataset, root, "raycast-aa", workers=1, progress=False)
    assert out.manifest["renderer"] == "raycast-aa"
    assert json.loads((root / "spec.json").read_text())["renderer"] == "raycast-aa"
    np.testing.assert_array_equal(out.split("train").targets, source.split("train").targets)
    changed = np.asarray(out.split("train").images) != np.asarray(source.split("train").images)
    assert changed.any()
    # an interrupted redraw: one run lost, a half-written file left; the same call finishes it
    first = min(stored_runs(root, "val"))
    path = run_path(root, "val", first)
    kept = path.read_bytes()
    path.unlink()
    path.with_name(path.name + ".tmp").write_bytes(b"partial")
    again = rerender(smoke_dataset, root, "raycast-aa", workers=1, progress=False)
    assert path.read_bytes() == kept
    assert not list(root.glob("runs/*/*.tmp"))
    assert again.id == out.id


def test_redrawing_refuses_its_own_source_and_an_unknown_renderer(smoke_dataset) -> None:
    with pytest.raises(DatasetError, match="another folder"):
        rerender(smoke_dataset, smoke_dataset, "raycast", workers=1, progress=False)
    with pytest.raises(ConfigError, match="unknown renderer"):
        rerender(smoke_dataset, smoke_dataset.parent / "x", "opengl", workers=1, progress=False)


def test_varied_scenes_change_the_ground_per_run_keep_the_drones_and_repeat(
    smoke_dataset, tmp_path
) -> None:
    source = open_dataset(smoke_dataset)
    root = tmp_path / "varied"
    out = rerender(smoke_dataset, root, "raycast-aa", workers=1, progress=False, vary_scene=3)
    plain = rerender(smoke_dataset, tmp_path / "plain", "raycast-aa", workers=1, progress=False)
    assert out.manifest["scene_variation"]["seed"] == 3
    assert out.id != plain.id  # a varied redraw is another dataset
    a, b = plain.split("train"), out.split("train")
    np.testing.assert_array_equal(a.targets, b.targets)
    # the sky and ground change, the drones stay: their dark pixels stay darker than any ground
    first = np.asarray(a.images).astype(int)
    varied = np.asarray(b.images).astype(int)
    assert np.abs(first - varied).mean() > 2.0
    drone = first < 60
    assert drone.sum() > 100
    assert (varied[drone] < 100).mean() > 0.9
    # two runs get two scenes: the mean sky brightness differs between runs
    runs = sorted(stored_runs(root, "train"))
    assert len(runs) >= 2
    tops = [np.load(run_path(root, "train", k))["images"][:, :8, :256].mean() for k in runs[:2]]
    assert abs(tops[0] - tops[1]) > 0.5
    # the same seed redraws the same bytes
    again = rerender(
        smoke_dataset, tmp_path / "again", "raycast-aa", workers=1, progress=False, vary_scene=3
    )
    assert again.id == out.id
    assert (
        run_path(root, "train", runs[0]).read_bytes()
        == run_path(tmp_path / "again", "train", runs[0]).read_bytes()
    )
    assert source.manifest["counts"] == out.manifest["counts"]


def test_a_negative_scene_seed_is_refused_naming_the_option(smoke_dataset, tmp_path) -> None:
    with pytest.raises(ConfigError, match="vary-scene"):
        rerender(
            smoke_dataset, tmp_path / "x", "raycast-aa", workers=1, progress=False, vary_scene=-1
        )
