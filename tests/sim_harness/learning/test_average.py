"""`swarm-sim average`: one network from the weighted mean of several networks' weights, written
as a policy the drone loads, with every source's history; bad shares refused before any read."""

import json

import pytest
import torch

from companion.errors import ConfigError, ModelError
from companion.model_file import load_model
from sim_harness.cli import main
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.average import average_networks, average_policies, require_weights
from sim_harness.learning.export import load_eager_model
from sim_harness.learning.model import build_model
from sim_harness.learning.train import TrainConfig, train


@pytest.fixture(scope="module")
def two_runs(smoke_dataset, tmp_path_factory):
    """A run from scratch (A) exported as a policy file, and a fine-tune of it (B, a run dir)."""
    root = tmp_path_factory.mktemp("average")

    def run(name: str, init_from=None):
        config = TrainConfig(
            dataset=smoke_dataset,
            out_dir=root / name,
            max_epochs=1,
            limit_train=32,
            progress=False,
            command=f"train {name}",
            init_from=init_from,
            seed=len(name),
        )
        train(config)
        return config.out_dir

    a_policy = root / "a.pt"
    export = ["export", "--checkpoint", str(run("A")), "--dataset", str(smoke_dataset)]
    assert main([*export, "--out", str(a_policy), "--eval-out", str(root / "eval-a")]) == 0
    b_run = run("BB", init_from=a_policy)
    return a_policy, b_run


def test_every_weight_is_the_weighted_mean_and_the_policy_loads(
    two_runs, smoke_dataset, tmp_path, capsys
) -> None:
    a_policy, b_run = two_runs
    out = tmp_path / "ab.pt"
    args = ["average", "--models", str(a_policy), str(b_run), "--weights", "0.25", "0.75"]
    args += ["--dataset", str(smoke_dataset), "--out", str(out), "--eval-out", str(tmp_path / "e")]
    assert main(args) == 0
    assert "test n = 180" in capsys.readouterr().out

    a, _ = load_eager_model(a_policy)
    b, _ = load_eager_model(b_run)
    mixed, metadata = load_eager_model(out)  # the weights file, verified through the policy
    sa, sb = a.state_dict(), b.state_dict()
    moved = 0
    for key, value in mixed.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(value, 0.25 * sa[key] + 0.75 * sb[key])
            moved += int(not torch.equal(sa[key], sb[key]))
    assert moved > 0  # the fine-tune changed something, so the mean is a new network

    # The file the drone loads answers as the averaged eager network does.
    images = torch.from_numpy(open_dataset(smoke_dataset).split("test").images[:4].copy())
    with torch.inference_mode():
        torch.testing.assert_close(load_model(out).module(images), mixed(images), atol=1e-4, rtol=0)

    training = metadata["training"]
    # B's chain holds A's: each command once, then the averaging command.
    assert training["chain"] == ["train A", "train BB", training["command"]]
    assert training["chain_complete"] is True
    assert [s["weight"] for s in training["averaged"]] == [0.25, 0.75]
    assert (
        training["averaged"][0]["sha256"]
        == json.loads(a_policy.with_suffix(".json").read_text())["sha256"]
    )
    assert metadata["test_metrics"]["split"] == "test"


def test_a_network_averaged_with_itself_answers_as_it_does(two_runs, smoke_dataset) -> None:
    a_policy, _ = two_runs
    same, sources = average_policies([a_policy, a_policy], [0.5, 0.5])
    original, _ = load_eager_model(a_policy)
    images = torch.from_numpy(open_dataset(smoke_dataset).split("test").images[:4].copy())
    with torch.inference_mode():
        torch.testing.assert_close(same(images), original(images), atol=1e-5, rtol=0)
    assert [s.weight for s in sources] == [0.5, 0.5]


@pytest.mark.parametrize(
    ("weights", "count", "message"),
    [
        ([0.5, 0.6], 2, "sum to 1"),
        ([1.2, -0.2], 2, "(0, 1]"),
        ([0.5, 0.5], 3, "one each"),
        ([float("nan"), 0.5], 2, "(0, 1]"),
        (None, 1, "at least 2"),
    ],
)
def test_bad_shares_are_refused_naming_the_field(weights, count, message) -> None:
    with pytest.raises(ConfigError, match="weights|models") as error:
        require_weights(weights, count)
    assert message in str(error.value)


def test_the_cli_refuses_bad_shares_before_reading_a_model(tmp_path, capsys) -> None:
    missing = [str(tmp_path / "none-a.pt"), str(tmp_path / "none-b.pt")]
    args = ["average", "--models", *missing, "--weights", "0.7", "0.7"]
    status = main([*args, "--dataset", str(tmp_path / "nothing"), "--out", str(tmp_path / "o.pt")])
    assert status != 0
    assert "weights: must sum to 1" in capsys.readouterr().err


def test_networks_of_other_architectures_are_refused() -> None:
    torch.manual_seed(0)
    resnet = build_model(pixel_mean=185.0, pixel_std=36.0)
    cube = build_model(pixel_mean=185.0, pixel_std=36.0, arch="cube")
    with pytest.raises(ModelError, match="differs from the first"):
        average_networks([resnet, cube], [0.5, 0.5])
    other_standardization = build_model(pixel_mean=120.0, pixel_std=36.0)
    with pytest.raises(ModelError, match="differs from the first"):
        average_networks([resnet, other_standardization], [0.5, 0.5])
