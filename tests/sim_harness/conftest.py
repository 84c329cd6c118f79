"""Shared fixtures of the simulation tests."""

from pathlib import Path

import pytest

from sim_harness.dataset.generate import generate
from sim_harness.dataset.spec import DatasetSpec


@pytest.fixture(scope="session")
def smoke_spec() -> DatasetSpec:
    """The `smoke` preset: 9 drones, runs cut at 2 s, a few hundred samples per split."""
    return DatasetSpec.preset("smoke")


@pytest.fixture(scope="session")
def smoke_dataset(tmp_path_factory: pytest.TempPathFactory, smoke_spec: DatasetSpec) -> Path:
    """Root of a generated smoke dataset (one worker, uninterrupted); treat it as read-only."""
    root = tmp_path_factory.mktemp("smoke") / "dataset"
    generate(root, smoke_spec, workers=1, progress=False, command="pytest smoke_dataset")
    return root


@pytest.fixture(scope="session")
def untrained_policy_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained ResNet-8 exported as a policy file (`.pt`, sidecar, eager weights), seeded.

    Its head gets random weights scaled so that it outputs speeds of about 1 m/s on random images
    (the model's initial head is zero; an He-initialized one gives tens of m/s, which the policy
    treats as a failure and zeroes). Independent of `models/`, so the tests run on a fresh clone.
    """
    import torch

    from sim_harness.learning.export import export_policy
    from sim_harness.learning.model import build_model

    torch.manual_seed(0)
    model = build_model(pixel_mean=120.0, pixel_std=50.0).eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.head.weight)
        probe = torch.randint(0, 256, (16, 64, 384), dtype=torch.uint8)
        model.head.weight.div_(model(probe).norm(dim=1).median())
    path = tmp_path_factory.mktemp("policy") / "untrained.pt"
    export_policy(model, path, {"id": "untrained-for-tests"}, None, {"command": "pytest fixture"})
    return path
