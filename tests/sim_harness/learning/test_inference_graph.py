"""The export's graph computes what the eager network computes, and the oneDNN Graph fuser
compiles all of its arithmetic but the input cast and pad."""

import re

import pytest
import torch
from torch import nn

from companion.model_file import enable_graph_fusion, graph_is_fused
from sim_harness.learning.export import to_torchscript
from sim_harness.learning.inference_graph import FoldedStem, InferenceDroNet
from sim_harness.learning.model import build_model


def _trained_looking_model() -> nn.Module:
    torch.manual_seed(3)
    model = build_model(pixel_mean=180.0, pixel_std=35.0)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.01)
        model.conv1.bias.normal_(0.0, 0.1)
        model.train()
        model(torch.randint(0, 256, (16, 64, 384), dtype=torch.uint8))  # batch-norm statistics
    return model.eval()


@pytest.fixture
def fusion_restored():
    before = torch.jit.onednn_fusion_enabled()
    yield
    enable_graph_fusion(before)


def test_folded_stem_equals_standardize_then_conv1_up_to_the_borders() -> None:
    model = _trained_looking_model()
    images = torch.randint(0, 256, (3, 64, 384), dtype=torch.uint8)
    images[0] = 0  # black everywhere: the zero padding of the standardized image matters most
    images[1, :, :3] = 255  # saturated left and top edges
    images[1, :3, :] = 255
    with torch.no_grad():
        expected = model.conv1(model.standardize(images))
        got = FoldedStem(model)(images)
    assert got.shape == expected.shape == (3, 32, 32, 192)
    assert (got - expected).abs().max().item() <= 1e-5 * max(1.0, expected.abs().max().item())


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


def test_the_exported_graph_carries_no_standardization_arithmetic() -> None:
    graph = str(to_torchscript(_trained_looking_model()).graph)
    assert "aten::sub" not in graph and "aten::div" not in graph
    assert "aten::pad" in graph or "aten::constant_pad_nd" in graph
    plain = str(to_torchscript(_trained_looking_model(), graph="eager").graph)
    assert "aten::sub" in plain and "aten::div" in plain


def _ops_outside_fusion_groups(graph: str) -> set[str]:
    top_level = graph.split("\nwith prim::oneDNNFusionGroup")[0]  # subgraphs are listed after
    return set(re.findall(r"= (aten::\w+)\(", top_level))


@pytest.mark.parametrize("batch", [1, 9])
def test_the_fuser_compiles_everything_but_the_input_cast_and_pad(
    batch: int, fusion_restored
) -> None:
    model = _trained_looking_model()
    assert enable_graph_fusion(True), "this torch build has no oneDNN Graph fuser"
    module = to_torchscript(model)
    images = torch.randint(0, 256, (batch, 64, 384), dtype=torch.uint8)
    with torch.inference_mode():
        for _ in range(3):  # profile, then compile the fused plan, then run it
            out = module(images)
        assert graph_is_fused()
        graph = str(torch.jit.last_executed_optimized_graph())
        assert (out - model(images)).abs().max().item() <= 1e-5
    outside = _ops_outside_fusion_groups(graph)
    cast_and_pad = {"aten::unsqueeze", "aten::to", "aten::pad", "aten::contiguous"}
    assert outside <= cast_and_pad | {"aten::flatten"}
    assert graph.count("with prim::oneDNNFusionGroup") >= 10  # convs, pool, batch norms, head


def test_without_the_fuser_the_graph_runs_unfused(fusion_restored) -> None:
    assert enable_graph_fusion(False) is False
    module = to_torchscript(_trained_looking_model())
    with torch.inference_mode():
        for _ in range(3):
            module(torch.zeros(1, 64, 384, dtype=torch.uint8))
        assert not graph_is_fused()
