"""The export's rewritten graph computes exactly what the eager network computes."""

import pytest
import torch
from torch import nn

from sim_harness.export import to_torchscript
from sim_harness.inference_graph import InferenceDroNet, ScaleShift, SlicedMaxPool
from sim_harness.model import build_model


@pytest.mark.parametrize("height,width", [(32, 192), (31, 95), (3, 3), (8, 7)])
def test_sliced_max_pool_equals_max_pool_3x3_stride_2(height, width) -> None:
    x = torch.randn(2, 5, height, width)
    x[0, 0, 0, :2] = 7.0  # ties pick the same value
    expected = nn.functional.max_pool2d(x, 3, stride=2)
    got = SlicedMaxPool(height, width)(x)
    assert torch.equal(got, expected)
    assert got.is_contiguous(memory_format=torch.channels_last)


def test_scale_shift_equals_the_batch_norm_it_folds() -> None:
    bn = nn.BatchNorm2d(6)
    with torch.no_grad():
        bn.weight.uniform_(0.5, 2.0)
        bn.bias.normal_()
        bn.running_mean.normal_()
        bn.running_var.uniform_(0.1, 3.0)
    x = torch.randn(3, 6, 4, 5)
    assert torch.allclose(ScaleShift(bn.eval())(x), bn(x), atol=1e-6)


def _trained_looking_model() -> nn.Module:
    torch.manual_seed(3)
    model = build_model(pixel_mean=180.0, pixel_std=35.0)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.01)
        model.train()
        model(torch.randint(0, 256, (16, 64, 384), dtype=torch.uint8))  # batch-norm statistics
    return model.eval()


def test_inference_graph_matches_the_network_and_leaves_it_untouched() -> None:
    model = _trained_looking_model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = InferenceDroNet(model).eval()
    images = torch.randint(0, 256, (5, 64, 384), dtype=torch.uint8)
    with torch.no_grad():
        assert (fast(images) - model(images)).abs().max().item() <= 1e-5
    assert model.training is False and all(
        torch.equal(before[k], v) for k, v in model.state_dict().items()
    )


def test_the_exported_graph_has_no_pool_with_indices_and_no_batch_norm() -> None:
    graph = str(to_torchscript(_trained_looking_model()).graph)
    assert "max_pool2d" not in graph and "batch_norm" not in graph
    assert graph.count("aten::thnn_conv2d") == 3  # the three 1x1 shortcuts
    plain = str(to_torchscript(_trained_looking_model(), graph="eager").graph)
    assert "max_pool2d" in plain and "batch_norm" in plain
