"""Grad-CAM: the 4x24 layer, maps in [0, 1], and saliency that lies on the drone in view."""

import numpy as np
import pytest
import torch

from companion.camera.layout import FACE_NAMES, FACE_SIZE_PX
from companion.errors import ConfigError
from sim_harness.cli import main
from sim_harness.learning.export import export_policy
from sim_harness.learning.gradcam import TARGETS, blend, grad_cam
from sim_harness.learning.model import DroNet, build_model
from sim_harness.sim.render import PyBulletRenderer
from sim_harness.sim.world import World

OBSERVER = np.array([0.0, 0.0, 5.0])
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def dark_blob_detector() -> DroNet:
    """A ResNet-8 whose weights are set by hand so that it responds to dark blobs only.

    Channel 0 carries "darkness" d = 1 - x / 255 (conv1's centre tap, pixel mean and std 255),
    thresholded at d > 0.7 by block 1's first batch norm (rendered drones are about 20-60 gray
    levels, ground and sky above 100), summed over 3x3 windows by each strided conv, passed on
    by the stride-1 convs' centre taps; the head adds up channel 0 into v_x. Every other weight
    is zero, so only what is dark can move the output.
    """
    model = build_model(pixel_mean=255.0, pixel_std=255.0).eval()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.Conv2d | torch.nn.Linear):
                module.weight.zero_()
                module.bias.zero_()
        model.conv1.weight[0, 0, 2, 2] = -1.0
        model.block1.bn1.bias[0] = -0.7
        for block in (model.block1, model.block2, model.block3):
            block.conv_strided.weight[0, 0] = 1.0
            block.conv.weight[0, 0, 1, 1] = 1.0
        model.head.weight[0, :24] = 1.0  # channel 0 of the flattened 128 x 2 x 12 map
    return model


def render_with_other_drone(other_offset_m) -> tuple[np.ndarray, np.ndarray]:
    """Observer's 64x384 image with the other drone at `other_offset_m` (world ENU, observer at
    yaw 0 so body = world axes), and the mask of pixels the other drone changes."""
    renderer = PyBulletRenderer()
    q = np.stack([IDENTITY, IDENTITY])
    with World(2) as world:
        image = renderer.render(world, np.stack([OBSERVER, OBSERVER + other_offset_m]), q, [0])
        empty = renderer.render(world, np.stack([OBSERVER, OBSERVER + 500.0]), q, [0])
    mask = np.abs(image[0].astype(int) - empty[0].astype(int)) > 20
    assert mask.sum() >= 4, "the other drone is not visible"
    return image[0], mask


def mass_near(heatmap: np.ndarray, mask: np.ndarray, margin_px: int) -> tuple[float, float]:
    """(fraction of the heatmap's total, fraction of the image's area) within `margin_px`
    (Chebyshev) of the masked pixels' bounding box."""
    rows, cols = np.nonzero(mask)
    near = np.zeros_like(mask)
    near[
        max(rows.min() - margin_px, 0) : rows.max() + margin_px + 1,
        max(cols.min() - margin_px, 0) : cols.max() + margin_px + 1,
    ] = True
    return float(heatmap[near].sum() / heatmap.sum()), float(near.mean())


@pytest.mark.parametrize(
    ("offset_m", "face"), [((1.8, 0.4, 0.4), "front"), ((-1.8, -0.4, 0.3), "back")]
)
def test_saliency_lies_on_the_single_drone_in_view(offset_m, face) -> None:
    image, drone = render_with_other_drone(np.array(offset_m))
    faces_hit = {FACE_NAMES[c // FACE_SIZE_PX] for c in np.nonzero(drone)[1]}
    assert faces_hit == {face}
    result = grad_cam(dark_blob_detector(), image, "speed")
    heat = result.heatmap[0]
    assert result.vel_body_flu[0, 0] > 0  # the detector saw the drone
    # Most of the saliency lies within one 16-px feature cell of the drone, a region that
    # covers about 6% of the image.
    heat_share, area_share = mass_near(heat, drone, 16)
    assert heat_share > 0.6 and area_share < 0.08
    # The hottest pixel is on the drone's cell, in the right face.
    row, col = np.unravel_index(np.argmax(heat), heat.shape)
    rows, cols = np.nonzero(drone)
    assert abs(row - rows.mean()) <= 16 and abs(col - cols.mean()) <= 16
    assert FACE_NAMES[col // FACE_SIZE_PX] == face


def test_maps_are_4x24_before_upsampling_and_in_unit_range() -> None:
    torch.manual_seed(0)
    model = build_model(pixel_mean=185.0, pixel_std=36.0)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.01)
    images = np.random.default_rng(0).integers(0, 256, (2, 64, 384), dtype=np.uint8)
    for target in TARGETS:
        result = grad_cam(model, images, target)
        assert result.cam.shape == (2, 4, 24)
        assert result.heatmap.shape == (2, 64, 384) and result.heatmap.dtype == np.float32
        assert result.heatmap.min() >= 0.0 and result.heatmap.max() == pytest.approx(1.0)
        single = grad_cam(model, images[1], target)  # samples do not interact
        np.testing.assert_allclose(single.heatmap[0], result.heatmap[1], atol=1e-5)
    with torch.no_grad():
        expected = model.eval()(torch.from_numpy(images))
    np.testing.assert_allclose(result.vel_body_flu, expected.numpy(), atol=1e-5)
    assert all(p.grad is None for p in model.parameters())  # nothing accumulated


def test_a_zero_command_has_an_empty_map_not_nan() -> None:
    model = build_model(pixel_mean=185.0, pixel_std=36.0)  # zero head: 0 m/s
    image = np.full((64, 384), 128, dtype=np.uint8)
    for target in TARGETS:
        heat = grad_cam(model, image, target).heatmap
        assert np.all(heat == 0.0)


def test_unknown_target_names_the_field() -> None:
    with pytest.raises(ConfigError, match="target"):
        grad_cam(build_model(185.0, 36.0), np.zeros((64, 384), np.uint8), "velocity")


def test_blend_is_rgb_with_the_heat_in_red() -> None:
    image = np.full((64, 384), 100, dtype=np.uint8)
    heat = np.zeros((64, 384), dtype=np.float32)
    heat[:, :64] = 1.0
    rgb = blend(image, heat)
    assert rgb.shape == (64, 384, 3) and rgb.dtype == np.uint8
    hot, cold = rgb[10, 10].astype(int), rgb[10, 200].astype(int)
    assert hot[0] > hot[2] and cold[2] > cold[0]  # jet: red where it matters, blue elsewhere


def test_swarm_sim_gradcam_writes_pngs(smoke_dataset, tmp_path) -> None:
    torch.manual_seed(0)
    model = build_model(pixel_mean=185.0, pixel_std=36.0)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.01)
    policy = tmp_path / "policy.pt"
    export_policy(model, policy, {"id": "smoke"}, None, {"command": "test"})
    out = tmp_path / "gradcam"
    args = ["gradcam", "--model", str(policy), "--dataset", str(smoke_dataset)]
    assert main([*args, "--samples", "0,5", "--out", str(out)]) == 0
    written = sorted(p.name for p in out.iterdir())
    assert written == ["test-000000.png", "test-000005.png"]
    assert all((out / name).stat().st_size > 10_000 for name in written)
    assert main([*args, "--samples", "100000", "--out", str(out)]) == 2
