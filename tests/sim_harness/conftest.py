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
