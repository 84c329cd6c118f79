"""`swarm-sim ensemble`: one policy file that calls several policies and averages their answers,
loaded by the drone as any policy, explained by Grad-CAM through its members; bad input refused
before anything is written."""

import json

import numpy as np
import pytest
import torch

from companion.errors import ModelError
from companion.model_file import load_model
from companion.policy import Policy, PolicyConfig
from sim_harness.cli import main
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.ensemble import EnsembleNet, load_eager_policy
from sim_harness.learning.export import export_policy, load_eager_model
from sim_harness.learning.gradcam import grad_cam
from sim_harness.learning.model import DroNet, build_model
from sim_harness.learning.symmetry import SymmetricPolicy


def network(seed: int, arch: str) -> DroNet:
    """A seeded network whose random head answers about 1 m/s (the initial head is zero)."""
    torch.manual_seed(seed)
    model = build_model(pixel_mean=180.0, pixel_std=40.0, arch=arch).eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.head.weight)
        probe = torch.randint(0, 256, (8, 64, 384), dtype=torch.uint8)
        model.head.weight.div_(model(probe).norm(dim=1).median())
    return model


@pytest.fixture(scope="module")
def members(smoke_dataset, tmp_path_factory):
    """Two policies of the smoke dataset that err differently: a ResNet-8 exported with the d4
    average, and a cube network exported bare."""
    root = tmp_path_factory.mktemp("ensemble")
    manifest = open_dataset(smoke_dataset).manifest
    a, b = root / "a.pt", root / "b.pt"
    export_policy(network(1, "dronet"), a, manifest, None, {"command": "a"}, symmetry="d4")
    export_policy(network(2, "cube"), b, manifest, None, {"command": "b"})
    return a, b


def run_ensemble(models, dataset, out, *extra) -> int:
    args = ["ensemble", "--models", *map(str, models), "--dataset", str(dataset)]
    return main([*args, "--out", str(out), "--eval-out", str(out.parent / "eval"), *extra])


def test_the_file_answers_the_weighted_mean_of_its_members_and_the_drone_loads_it(
    members, smoke_dataset, tmp_path, capsys
) -> None:
    a, b = members
    out = tmp_path / "ab.pt"
    assert run_ensemble(members, smoke_dataset, out, "--weights", "0.3", "0.7") == 0
    assert "test n = 180" in capsys.readouterr().out

    images = torch.from_numpy(open_dataset(smoke_dataset).split("test").images[:6].copy())
    with torch.inference_mode():
        expected = 0.3 * load_model(a).module(images) + 0.7 * load_model(b).module(images)
        torch.testing.assert_close(load_model(out).module(images), expected, atol=1e-5, rtol=0)

    # The drone's loader: hash, metadata, warm-up and the platform check's reference.
    policy = Policy.load(PolicyConfig(model_path=out))
    got = policy.infer_batch(images.numpy(), zero_invalid=False)
    np.testing.assert_allclose(got, expected.numpy(), atol=1e-4)

    metadata = json.loads(out.with_suffix(".json").read_text())["metadata"]
    listed = metadata["ensemble"]
    assert [m["weight"] for m in listed] == [0.3, 0.7]
    assert [m["arch"] for m in listed] == ["dronet", "cube"]
    assert [m["symmetry"] for m in listed] == ["d4", "none"]
    assert listed[0]["sha256"] == json.loads(a.with_suffix(".json").read_text())["sha256"]
    symmetry = metadata["runtime"]["symmetry"]
    assert symmetry["views"] == 9  # 8 + 1 network calls an image
    assert (symmetry["group"], symmetry["members"]) == ("none", ["d4", "none"])
    assert metadata["test_metrics"]["split"] == "test"
    assert metadata["training"]["chain"][:2] == ["a", "b"]

    # Grad-CAM's eager form: the bare members (no symmetry average) with their shares.
    eager, _ = load_eager_policy(out)
    assert isinstance(eager, EnsembleNet)
    bare_a, _ = load_eager_model(a)
    bare_b, _ = load_eager_model(b)
    with torch.inference_mode():
        torch.testing.assert_close(
            SymmetricPolicy(eager.members[0], "d4")(images), SymmetricPolicy(bare_a, "d4")(images)
        )
        torch.testing.assert_close(
            eager(images), 0.3 * bare_a(images) + 0.7 * bare_b(images), atol=1e-5, rtol=0
        )
    # One network's tools refuse it by name.
    with pytest.raises(ModelError, match="ensemble of 2 networks"):
        load_eager_model(out)


def test_grad_cam_of_an_ensemble_of_one_network_twice_is_that_networks(members) -> None:
    single, _ = load_eager_model(members[1])
    twice = EnsembleNet([single, single], [0.5, 0.5])
    image = np.random.default_rng(0).integers(0, 256, (64, 384), dtype=np.uint8)
    for target in ("speed", "y"):
        alone, both = grad_cam(single, image, target), grad_cam(twice, image, target)
        np.testing.assert_allclose(both.vel_body_flu, alone.vel_body_flu, atol=1e-6)
        np.testing.assert_allclose(both.cam, alone.cam, rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(both.heatmap, alone.heatmap, atol=1e-5)


def test_grad_cam_command_explains_an_ensemble_file(members, smoke_dataset, tmp_path) -> None:
    out = tmp_path / "ab.pt"
    assert run_ensemble(members, smoke_dataset, out) == 0
    args = ["gradcam", "--model", str(out), "--dataset", str(smoke_dataset), "--samples", "0"]
    assert main([*args, "--out", str(tmp_path / "cam")]) == 0
    assert (tmp_path / "cam" / "test-000000.png").stat().st_size > 0


def test_bad_shares_and_counts_are_refused_before_anything_is_read(tmp_path, capsys) -> None:
    missing = [tmp_path / "none1.pt", tmp_path / "none2.pt"]
    refusals = {
        "weights: must sum to 1, got 1.1": (missing, ["--weights", "0.5", "0.6"], "x.pt"),
        "models: an ensemble takes 2 to 8 policies, got 9": (missing * 4 + missing[:1], [], "x.pt"),
        "models: an ensemble needs at least 2 networks, got 1": (missing[:1], [], "x.pt"),
        "out: the policy file must end in .pt": (missing, [], "x.json"),
    }
    for message, (models, extra, out) in refusals.items():
        assert run_ensemble(models, tmp_path / "no-data", tmp_path / out, *extra) == 2
        assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_nested_ensemble_another_dataset_or_a_tampered_member_is_refused(
    members, smoke_dataset, tmp_path, capsys
) -> None:
    a = members[0]
    inner = tmp_path / "inner" / "ab.pt"
    assert run_ensemble(members, smoke_dataset, inner) == 0
    assert run_ensemble([inner, a], smoke_dataset, tmp_path / "nested.pt") == 2
    assert f"{inner} is itself an ensemble: list its members instead" in capsys.readouterr().err

    other = tmp_path / "other.pt"
    export_policy(network(3, "dronet"), other, {"id": "another-dataset"}, None, {"command": "o"})
    assert run_ensemble([a, other], smoke_dataset, tmp_path / "mixed.pt") == 2
    assert "was trained on dataset another-dataset" in capsys.readouterr().err

    weights = inner.with_name("ab.weights.pt")
    weights.write_bytes(weights.read_bytes() + b"\0")
    with pytest.raises(ModelError, match="does not match the hash"):
        load_eager_policy(inner)
    assert not (tmp_path / "nested.pt").exists() and not (tmp_path / "mixed.pt").exists()
