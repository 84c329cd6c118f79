"""Choosing the renderer: by name, recorded with datasets, a warning on a mismatch."""

import argparse
import json
import logging

import numpy as np
import pytest

from sim_harness.dataset.spec import DatasetSpec
from sim_harness.errors import ConfigError
from sim_harness.sim.raycast import RaycastRenderer
from sim_harness.sim.render import PyBulletRenderer
from sim_harness.sim.renderers import (
    RENDERERS,
    add_renderer_option,
    make_renderer,
    model_renderer,
    renderer_of_model,
    warn_if_trained_elsewhere,
)
from sim_harness.sim.scene import SCENE_RANGES, SceneSpec, ground_texture, random_scene
from sim_harness.sim.world import World


def test_names_make_their_renderers() -> None:
    assert isinstance(make_renderer("pybullet"), PyBulletRenderer)
    assert isinstance(make_renderer("raycast"), RaycastRenderer)
    aa = make_renderer("raycast-aa")
    assert isinstance(aa, RaycastRenderer) and aa.supersample == 4 and aa.name == "raycast-aa"
    with pytest.raises(ConfigError, match="unknown renderer 'opengl'"):
        make_renderer("opengl")


def test_the_option_defaults_to_pybullet_and_refuses_others() -> None:
    parser = argparse.ArgumentParser()
    add_renderer_option(parser)
    assert parser.parse_args([]).renderer == "pybullet"
    assert parser.parse_args(["--renderer", "raycast"]).renderer == "raycast"
    with pytest.raises(SystemExit):
        parser.parse_args(["--renderer", "opengl"])
    assert RENDERERS == ("pybullet", "raycast", "raycast-aa")


def test_a_command_that_flies_a_model_leaves_the_choice_to_the_model() -> None:
    parser = argparse.ArgumentParser()
    add_renderer_option(parser, follows_model=True)
    assert parser.parse_args([]).renderer is None  # resolved with renderer_of_model
    assert parser.parse_args(["--renderer", "raycast-aa"]).renderer == "raycast-aa"


def test_the_model_file_names_its_training_renderer(tmp_path) -> None:
    model = tmp_path / "policy.pt"
    assert renderer_of_model(model) == "pybullet"  # no sidecar: loading refuses it later
    sidecar = tmp_path / "policy.json"
    sidecar.write_text(json.dumps({"sha256": "0", "metadata": {"dataset": {"id": "x"}}}))
    assert renderer_of_model(model) == "pybullet"  # exported before datasets recorded it
    metadata = {"dataset": {"id": "x", "renderer": "raycast-aa"}}
    sidecar.write_text(json.dumps({"sha256": "0", "metadata": metadata}))
    assert renderer_of_model(model) == "raycast-aa"
    sidecar.write_text("{not json")
    assert renderer_of_model(model) == "pybullet"


def test_dataset_spec_records_the_renderer_and_keeps_old_ids() -> None:
    pybullet, raycast = DatasetSpec(), DatasetSpec(renderer="raycast")
    assert "renderer" not in pybullet.content_dict()  # ids of datasets made before the option
    assert pybullet.as_dict()["renderer"] == "pybullet"
    assert raycast.content_id() != pybullet.content_id()
    assert DatasetSpec.from_dict(raycast.as_dict()) == raycast
    with pytest.raises(ConfigError, match="dataset.renderer"):
        DatasetSpec(renderer="opengl")


def test_a_flight_on_another_renderer_warns_once(caplog) -> None:
    trained_raycast = {"dataset": {"id": "x", "renderer": "raycast"}}
    with caplog.at_level(logging.WARNING):
        assert warn_if_trained_elsewhere(trained_raycast, "pybullet")
        assert not warn_if_trained_elsewhere(trained_raycast, "raycast")
        assert not warn_if_trained_elsewhere({"dataset": {"id": "old"}}, "pybullet")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "trained on raycast images" in warnings[0].getMessage()
    assert model_renderer({}) == "pybullet"


def test_random_scenes_stay_in_their_ranges_and_keep_the_ground_above_the_drones() -> None:
    rng = np.random.default_rng(0)
    scenes = [random_scene(rng) for _ in range(50)]
    assert len({s.ground_seed for s in scenes}) == 50
    for s in scenes:
        assert SCENE_RANGES["ground_mean"][0] <= s.ground_mean <= SCENE_RANGES["ground_mean"][1]
        assert (
            SCENE_RANGES["ground_tile_m"][0] <= s.ground_tile_m <= SCENE_RANGES["ground_tile_m"][1]
        )
        assert s.sky_zenith_gray < s.sky_horizon_gray
    texture = ground_texture(scenes[0])
    assert texture.min() >= 100 and texture.max() <= 210


def test_a_renderer_draws_the_scene_it_is_given() -> None:
    pos = np.array([[0.0, 0.0, 5.0]])
    level = np.array([[1.0, 0.0, 0.0, 0.0]])
    dull = SceneSpec(sky_horizon_gray=215.0, sky_zenith_gray=170.0)
    with World(1) as world:
        default = make_renderer("raycast").render(world, pos, level).astype(int)
        other = make_renderer("raycast", dull).render(world, pos, level).astype(int)
    top_rows = slice(0, 8)  # the lateral faces' upper rows: sky
    assert (default[0, top_rows, :256] - other[0, top_rows, :256]).mean() > 10.0
