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
