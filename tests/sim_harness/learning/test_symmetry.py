"""The rig's symmetric views are what a turned or mirrored drone really sees, with the label the
teacher really gives it; the symmetrized policy is exactly equivariant and cancels a body bias."""

import json

import numpy as np
import pytest
import torch
from torch import nn

from companion.errors import ConfigError
from companion.flocking import FlockingParams
from companion.frames import quat_from_euler_zyx, quat_from_yaw, quat_multiply
from companion.model_file import load_model
from sim_harness.dataset.runs import teacher_targets
from sim_harness.learning.export import export_policy
from sim_harness.learning.model import build_model
from sim_harness.learning.symmetry import (
    GROUPS,
    SymmetricPolicy,
    augment,
    label_matrix,
    require_group,
    view_image,
)
from sim_harness.learning.symmetry_views import pixel_source
from sim_harness.learning.train_config import TrainConfig
from sim_harness.sim.raycast import RaycastRenderer
from sim_harness.sim.world import World

OBSERVER = np.array([0.0, 0.0, 5.0])
NEIGHBOURS = np.array([[1.5, 0.4, 0.2], [-0.8, 2.0, -0.5], [0.3, -1.2, 1.5], [-2.5, -1.0, 0.4]])
NEIGHBOUR_YAWS = (0.3, 1.1, -0.4, 2.0)
QUARTER_LEFT = quat_from_yaw(np.pi / 2)


@pytest.fixture(scope="module")
def world():
    with World(1 + len(NEIGHBOURS)) as w:
        yield w


def _scene(observer_q, neighbours=NEIGHBOURS, yaws=NEIGHBOUR_YAWS):
    pos = np.vstack([OBSERVER, OBSERVER + neighbours])
    q = np.stack([observer_q, *(quat_from_yaw(y) for y in yaws)])
    return pos, q


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.0, 0.0, 0.7), (0.15, -0.1, 2.3)])
def test_a_quarter_turn_left_is_the_reordered_image_and_the_turned_label(world, rpy) -> None:
    # Pixel centres sampled (offset 0.5): the square pixel grid is then exactly symmetric.
    renderer = RaycastRenderer(sample_offset_px=(0.5, 0.5))
    q = quat_from_euler_zyx(*rpy)
    turned = quat_multiply(q, QUARTER_LEFT)  # about the body's own z axis, tilted or not
    pos, quats = _scene(q)
    before = renderer.render(world, pos, quats, [0])[0]
    quats[0] = turned
    after = renderer.render(world, pos, quats, [0])[0]
    assert np.abs(before.astype(int) - after.astype(int)).mean() > 5  # the view really changed
    np.testing.assert_array_equal(view_image(before, (1, False)), after)
    params = FlockingParams()
    label = teacher_targets(pos, _scene(q)[1], params)["rey_body"][0]
    label_turned = teacher_targets(pos, quats, params)["rey_body"][0]
    np.testing.assert_allclose(label_matrix((1, False)) @ label, label_turned, atol=1e-12)


def test_the_mirror_view_shows_the_mirrored_flock_and_gets_the_mirrored_label(world) -> None:
    # The ground's texture is not mirror-symmetric, so compare the drones' pixels: those that
    # differ from the same view with every neighbour far away.
    renderer = RaycastRenderer(sample_offset_px=(0.5, 0.5))
    level = quat_from_yaw(0.0)
    flip = np.array([1.0, -1.0, 1.0])
    far = np.full_like(NEIGHBOURS, 5000.0)
    pos, q = _scene(level)
    mpos, mq = _scene(level, NEIGHBOURS * flip, tuple(-y for y in NEIGHBOUR_YAWS))
    empty = renderer.render(world, *_scene(level, far), [0])[0]
    drones = renderer.render(world, pos, q, [0])[0] != empty
    mirrored_drones = renderer.render(world, mpos, mq, [0])[0] != empty
    assert drones.sum() > 30  # four drones 1.5-2.7 m away, thin arms
    np.testing.assert_array_equal(view_image(drones, (0, True)), mirrored_drones)
    params = FlockingParams()
    label = teacher_targets(pos, q, params)["rey_body"][0]
    mirrored_label = teacher_targets(mpos, mq, params)["rey_body"][0]
    np.testing.assert_allclose(label_matrix((0, True)) @ label, mirrored_label, atol=1e-12)


@pytest.mark.parametrize("group", list(GROUPS))
def test_each_group_is_closed_and_its_views_are_pixel_permutations(group) -> None:
    views = GROUPS[group]
    images = np.random.default_rng(0).integers(0, 256, (len(views), 64, 384), dtype=np.uint8)
    for a in views:
        source = pixel_source(a)
        assert np.array_equal(np.sort(source), np.arange(64 * 384))
        for b in views:  # b after a is again a view of the group, image and label alike
            composed = view_image(view_image(images[0], a), b)
            matches = [v for v in views if np.array_equal(view_image(images[0], v), composed)]
            assert len(matches) == 1
            np.testing.assert_allclose(
                label_matrix(b) @ label_matrix(a), label_matrix(matches[0]), atol=1e-12
            )


def _random_net() -> nn.Module:
    torch.manual_seed(1)
    model = build_model(pixel_mean=150.0, pixel_std=40.0)
    with torch.no_grad():
        nn.init.normal_(model.head.weight, std=0.05)
        model.head.bias.copy_(torch.tensor([0.3, -0.2, 0.1]))  # a body-frame bias
    return model.eval()


def test_the_symmetrized_policy_is_equivariant_and_cancels_a_horizontal_bias() -> None:
    net = _random_net()
    policy = SymmetricPolicy(net, "d4").eval()
    images = torch.randint(0, 256, (3, 64, 384), dtype=torch.uint8)
    with torch.no_grad():
        out = policy(images).double().numpy()
        for view in GROUPS["d4"]:
            seen = torch.from_numpy(view_image(images.numpy(), view))
            expected = out @ label_matrix(view).T
            np.testing.assert_allclose(policy(seen).double().numpy(), expected, atol=2e-5)
        blank = torch.full((1, 64, 384), 184, dtype=torch.uint8)  # same in every view
        plain = net(blank)[0]
        sym = SymmetricPolicy(net, "c4")(blank)[0]
    assert abs(float(plain[0])) > 0.1 and abs(float(plain[1])) > 0.1
    np.testing.assert_allclose(sym[:2].numpy(), 0.0, atol=1e-5)  # horizontal bias gone
    assert float(sym[2]) == pytest.approx(float(plain[2]), abs=1e-5)  # vertical kept


def test_augmented_samples_are_views_of_their_originals_with_matching_labels() -> None:
    rng = np.random.default_rng(2)
    images = torch.from_numpy(rng.integers(0, 256, (64, 64, 384), dtype=np.uint8))
    targets = torch.from_numpy(rng.normal(size=(64, 3)).astype(np.float32))
    seen, labels = augment(images, targets, torch.Generator().manual_seed(0), "d4")
    used = set()
    for i in range(len(images)):
        view = next(
            v
            for v in GROUPS["d4"]
            if np.array_equal(view_image(images[i].numpy(), v), seen[i].numpy())
        )
        used.add(view)
        expected = label_matrix(view) @ targets[i].double().numpy()
        np.testing.assert_allclose(labels[i].numpy(), expected, atol=1e-6)
    assert len(used) == 8  # 64 draws visit every view
    same, _ = augment(images, targets, torch.Generator().manual_seed(0), "d4")
    assert torch.equal(same, seen)  # reproducible from the seed (a resumed epoch repeats it)


def test_an_unknown_group_is_refused_naming_the_field(tmp_path) -> None:
    with pytest.raises(ConfigError, match="augment: unknown symmetry group 'd8'"):
        TrainConfig(dataset=tmp_path, out_dir=tmp_path, augment="d8")
    with pytest.raises(ConfigError, match="choose one of none, mirror, c4, d4"):
        require_group("all")


def test_a_symmetrized_export_loads_records_its_group_and_computes_the_average(tmp_path) -> None:
    net = _random_net()
    path = tmp_path / "sym.pt"
    result = export_policy(net, path, {"id": "sym-test"}, None, {"command": "test"}, symmetry="c4")
    loaded = load_model(path)
    assert loaded.metadata["runtime"]["symmetry"]["group"] == "c4"
    assert loaded.metadata["runtime"]["symmetry"]["views"] == 4
    images = torch.randint(0, 256, (2, 64, 384), dtype=torch.uint8)
    with torch.no_grad():
        by_hand = torch.stack(
            [
                net(torch.from_numpy(view_image(images.numpy(), v))).double()
                @ torch.from_numpy(label_matrix(v))
                for v in GROUPS["c4"]
            ]
        ).mean(0)
        # the export's own bound (`max_abs_diff_mps` below): the frozen graph folds the
        # standardization into conv1, so float32 rounding differs from the eager network's by a
        # few 1e-5 m/s, more on some CPUs' kernels (2.4e-5 seen on an AMD EPYC)
        np.testing.assert_allclose(loaded.module(images).double(), by_hand, atol=1e-4)
    assert result.max_abs_diff_mps <= 1e-4
    record = json.loads(path.with_suffix(".json").read_text())
    assert record["metadata"]["runtime"]["symmetry"]["group"] == "c4"
