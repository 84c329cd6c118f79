"""The policy network: shapes, size, the Grad-CAM layer, standardization inside, initialization."""

import math

import pytest
import torch

from companion.camera.layout import IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.errors import ConfigError
from sim_harness.learning.model import (
    DroNet,
    build_model,
    count_parameters,
    decayed_parameters,
    example_input,
    parameter_groups,
)


@pytest.fixture(scope="module")
def model() -> DroNet:
    torch.manual_seed(0)
    return build_model(pixel_mean=180.0, pixel_std=35.0).eval()


def feature_shapes(model: DroNet, batch: int) -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    layers = {
        "conv1": model.conv1,
        "pool": model.pool,
        "block1": model.block1,
        "block2": model.block2,
        "gradcam": model.gradcam_layer,
        "block3": model.block3,
    }
    hooks = [
        layer.register_forward_hook(
            lambda _m, _i, out, name=name: shapes.__setitem__(name, tuple(out.shape))
        )
        for name, layer in layers.items()
    ]
    with torch.no_grad():
        model(example_input(batch))
    for hook in hooks:
        hook.remove()
    return shapes


@pytest.mark.parametrize("batch", [1, 9])
def test_uint8_images_in_body_velocity_out(model, batch) -> None:
    images = torch.randint(0, 256, (batch, 64, 384), dtype=torch.uint8)
    with torch.no_grad():
        out = model(images)
    assert out.shape == (batch, 3) and out.dtype == torch.float32


def test_feature_maps_follow_dronet_and_the_gradcam_layer_is_4x24(model) -> None:
    shapes = feature_shapes(model, 2)
    assert shapes["conv1"] == (2, 32, 32, 192)
    assert shapes["pool"] == (2, 32, 15, 95)
    assert shapes["block1"] == (2, 32, 8, 48)
    assert shapes["gradcam"] == (2, 64, 4, 24)
    assert shapes["block2"] == (2, 64, 4, 24)
    assert shapes["block3"] == (2, 128, 2, 12)
    assert model.gradcam_layer is model.block2.conv_strided
    assert model.gradcam_layer.stride == (2, 2) and model.gradcam_layer.kernel_size == (3, 3)


def conv_parameters(kernel: int, c_in: int, c_out: int) -> int:
    return kernel * kernel * c_in * c_out + c_out  # weights and biases


def block_parameters(c_in: int, c_out: int) -> int:
    """BN-conv3x3/2, BN-conv3x3/1 and the 1x1 shortcut (a batch norm has a scale and a shift)."""
    return (
        2 * c_in
        + conv_parameters(3, c_in, c_out)
        + 2 * c_out
        + conv_parameters(3, c_out, c_out)
        + conv_parameters(1, c_in, c_out)
    )


def feature_size(n: int, kernel: int, stride: int, padding: int) -> int:
    return (n + 2 * padding - kernel) // stride + 1


def test_about_318k_parameters(model) -> None:
    """Counted from the architecture in the module docstring, not copied from the model."""
    rows, cols = IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
    for kernel, stride, padding in [(5, 2, 2), (3, 2, 0)] + [(3, 2, 1)] * 3:  # conv1, pool, blocks
        rows, cols = (
            feature_size(rows, kernel, stride, padding),
            feature_size(cols, kernel, stride, padding),
        )
    expected = (
        conv_parameters(5, 1, 32)
        + block_parameters(32, 32)
        + block_parameters(32, 64)
        + block_parameters(64, 128)
        + 2 * 128  # bn_out
        + 128 * rows * cols * 3
        + 3  # the linear head
    )
    n = count_parameters(model)
    assert n == expected
    assert abs(n - 318_000) / 318_000 < 0.01  # DroNet-style ResNet-8 on 1x64x384: ~318k


def test_standardization_is_inside_and_travels_with_the_weights(model) -> None:
    x = torch.full((1, 64, 384), 180, dtype=torch.uint8)
    x[0, 0, 1] = 215  # mean + one std
    standardized = model.standardize(x)
    assert standardized.shape == (1, 1, 64, 384) and standardized.dtype == torch.float32
    assert standardized[0, 0, 0, 0].item() == pytest.approx(0.0)
    assert standardized[0, 0, 0, 1].item() == pytest.approx(1.0)
    state = model.state_dict()
    assert state["standardize.pixel_mean"].item() == 180.0
    assert state["standardize.pixel_std"].item() == 35.0
    assert "standardize.pixel_mean" not in dict(model.named_parameters())


def test_channels_last_on_cpu(model) -> None:
    assert model.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    assert model.block3.conv.weight.is_contiguous(memory_format=torch.channels_last)
    assert model.standardize(example_input(2)).is_contiguous(memory_format=torch.channels_last)


def truncated_normal_std(a: float) -> float:
    """The std of a unit normal truncated to [-a, a]: sqrt(1 - 2 a phi(a) / (2 Phi(a) - 1))."""
    pdf = math.exp(-a * a / 2.0) / math.sqrt(2.0 * math.pi)
    mass = math.erf(a / math.sqrt(2.0))  # 2 Phi(a) - 1
    return math.sqrt(1.0 - 2.0 * a * pdf / mass)


TRUNCATED_STD = truncated_normal_std(2.0)  # He's truncated normal is cut at two sigma


def test_he_truncated_normal_weights_zero_biases_identity_norms() -> None:
    torch.manual_seed(1)
    model = build_model(pixel_mean=128.0, pixel_std=64.0)
    for name, weight in decayed_parameters(model):
        if name == "head.weight":
            continue
        fan_in = weight[0].numel()
        target_std = math.sqrt(2.0 / fan_in)
        bound = 2.0 * target_std / TRUNCATED_STD
        assert weight.abs().max().item() <= bound + 1e-6, name  # truncated at 2 sigma
        if weight.numel() > 10_000:
            assert weight.std().item() == pytest.approx(target_std, rel=0.03), name
    for module in model.modules():
        if isinstance(module, torch.nn.Conv2d | torch.nn.Linear):
            assert torch.count_nonzero(module.bias) == 0
        if isinstance(module, torch.nn.BatchNorm2d):
            assert torch.all(module.weight == 1) and torch.all(module.bias == 0)
    # The head starts at zero: an untrained policy commands 0 m/s (hover), not +-10 m/s.
    assert torch.count_nonzero(model.head.weight) == 0
    with torch.no_grad():
        assert torch.all(model.eval()(example_input(3)) == 0)


def test_weight_decay_groups_hold_weights_only(model) -> None:
    groups = parameter_groups(model, 5e-4)
    decayed, plain = groups
    assert decayed["weight_decay"] == 5e-4 and plain["weight_decay"] == 0.0
    names = {id(p): n for n, p in model.named_parameters()}
    decayed_names = {names[id(p)] for p in decayed["params"]}
    plain_names = {names[id(p)] for p in plain["params"]}
    assert decayed_names.isdisjoint(plain_names)
    assert decayed_names | plain_names == set(names.values())
    assert all(n.endswith(".weight") for n in decayed_names)
    assert all(p.ndim > 1 for p in decayed["params"])  # conv kernels and the linear matrix
    assert "head.weight" in decayed_names and "conv1.weight" in decayed_names
    assert "head.bias" in plain_names and "block2.bn1.weight" in plain_names
    assert len(decayed_names) == 1 + 3 * 3 + 1  # conv1, three convs per block, head


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"pixel_mean": 180.0, "pixel_std": 0.0}, "pixel_std"),
        ({"pixel_mean": 300.0, "pixel_std": 30.0}, "pixel_mean"),
        ({"pixel_mean": 180.0, "pixel_std": 30.0, "dropout": 1.0}, "dropout"),
    ],
)
def test_bad_settings_name_the_field(kwargs, field) -> None:
    with pytest.raises(ConfigError, match=field):
        DroNet(**kwargs)
