"""The exported policy: equal to the eager network, self-describing, loads with torch alone,
refused when its bytes do not match the recorded hash."""

import asyncio
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from companion.camera.layout import camera_spec
from companion.errors import ModelError
from companion.model_file import enable_graph_fusion, load_model, sidecar_path
from companion.policy import Policy, PolicyConfig
from sim_harness.cli import main
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.export import (
    add_reference,
    export_policy,
    load_eager_model,
    training_chain,
    weights_path_for,
)
from sim_harness.learning.model import DroNet, build_model, count_parameters
from sim_harness.learning.train import TrainConfig, train

FRESH_INTERPRETER = r"""
import importlib.abc, json, sys

class NoProject(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("companion", "sim_harness"):
            raise ImportError(f"{name} must not be needed to run the policy")
        return None

sys.meta_path.insert(0, NoProject())
import torch

extra = {"metadata.json": ""}
module = torch.jit.load(sys.argv[1], _extra_files=extra)
images = torch.zeros(2, 64, 384, dtype=torch.uint8)
images[1] = torch.arange(384, dtype=torch.uint8)  # a gradient, row after row
with torch.inference_mode():
    out = module(images)
print(json.dumps({
    "dtype": str(out.dtype),
    "shape": list(out.shape),
    "out": out.tolist(),
    "output_frame": json.loads(extra["metadata.json"])["output"]["frame"],
    "project_loaded": sorted(
        m for m in sys.modules if m.split(".")[0] in ("companion", "sim_harness")
    ),
}))
"""


def trained_looking(images_u8: torch.Tensor, seed: int = 0) -> DroNet:
    """An untrained network made to look trained: batch-norm statistics estimated on real
    images, affine parameters away from the identity (so freezing folds something), and a head
    giving speeds of about 1 m/s."""
    torch.manual_seed(seed)
    model = build_model(pixel_mean=185.0, pixel_std=36.0)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                n = module.num_features
                module.weight.copy_(torch.rand(n, generator=generator) + 0.5)
                module.bias.copy_(torch.randn(n, generator=generator) * 0.1)
                module.reset_running_stats()
                module.momentum = None  # a plain average over the batches below
        model.train()
        for batch in images_u8.split(32):
            model(batch)
        model.head.weight.copy_(torch.randn(3, 3072, generator=generator) * 0.01)
        model.head.bias.copy_(torch.tensor([0.1, -0.2, 0.05]))
    return model.eval()


@pytest.fixture(scope="module")
def exported(smoke_dataset, tmp_path_factory):
    dataset = open_dataset(smoke_dataset)
    model = trained_looking(torch.from_numpy(np.array(dataset.split("train").images[:96])))
    path = tmp_path_factory.mktemp("export") / "policy.pt"
    metrics = {"split": "test", "metrics": {"overall": {"r2": 0.5}}}
    training = {"command": "swarm-sim train --dataset smoke", "epochs_run": 7}
    result = export_policy(model, path, dataset.manifest, metrics, training)
    return model, result, dataset


def test_exported_equals_eager_within_1e5(exported) -> None:
    model, result, dataset = exported
    module = load_model(result.path).module
    test = dataset.split("test")
    real = torch.from_numpy(np.array(test.images[:9]))
    noise = torch.randint(
        0, 256, (9, 64, 384), dtype=torch.uint8, generator=torch.Generator().manual_seed(1)
    )
    with torch.inference_mode():
        for images in (real, noise, real[:1]):
            eager, frozen = model(images), module(images)
            assert frozen.shape == (images.shape[0], 3) and frozen.dtype == torch.float32
            assert 0.3 < eager.abs().max() < 10.0  # speeds a drone flies
            assert (frozen - eager).abs().max().item() <= 1e-5
    assert result.max_abs_diff_mps <= 1e-5


@pytest.mark.parametrize("fusion", [True, False])
def test_the_drone_loader_runs_the_export_fused_and_equal_to_eager(exported, fusion) -> None:
    model, result, dataset = exported
    fusion_before = torch.jit.onednn_fusion_enabled()
    images = np.array(dataset.split("test").images[:9])
    try:
        with Policy.load(PolicyConfig(model_path=result.path, graph_fusion=fusion)) as policy:
            assert policy.fused is fusion  # this x86 torch build has the oneDNN Graph fuser
            one = asyncio.run(policy.infer(images[0]))
            batch = policy.infer_batch(images)
    finally:
        enable_graph_fusion(fusion_before)
    with torch.inference_mode():
        eager = model(torch.from_numpy(images)).numpy()
    assert one.ok
    np.testing.assert_allclose(one.vel_body_flu, eager[0], atol=1e-5, rtol=0)
    np.testing.assert_allclose(batch, eager, atol=1e-5, rtol=0)  # another batch size re-plans


def test_loads_and_runs_in_a_fresh_interpreter_with_torch_only(exported, tmp_path) -> None:
    model, result, _ = exported
    done = subprocess.run(
        [sys.executable, "-c", FRESH_INTERPRETER, str(result.path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["project_loaded"] == []
    assert report["dtype"] == "torch.float32" and report["shape"] == [2, 3]
    assert report["output_frame"] == "body_flu"
    images = torch.zeros(2, 64, 384, dtype=torch.uint8)
    images[1] = torch.arange(384, dtype=torch.uint8)
    with torch.inference_mode():
        expected = model(images).numpy()
    np.testing.assert_allclose(np.array(report["out"]), expected, atol=1e-5, rtol=0)


def test_metadata_travels_with_the_file(exported) -> None:
    model, result, dataset = exported
    metadata = load_model(result.path).metadata
    assert metadata == json.loads(sidecar_path(result.path).read_text())["metadata"]
    assert metadata["input"]["dtype"] == "uint8" and metadata["input"]["shape"] == [-1, 64, 384]
    assert metadata["input"]["standardization"] == "inside"
    assert metadata["output"] == {"frame": "body_flu", "units": "m/s", "shape": [-1, 3]}
    assert metadata["camera"] == camera_spec()
    assert metadata["frames"]["world"] == "ENU" and "FLU" in metadata["frames"]["output"]
    assert metadata["dataset"]["id"] == dataset.id
    assert metadata["pixel_mean"] == 185.0 and metadata["pixel_std"] == 36.0
    assert metadata["test_metrics"]["metrics"]["overall"]["r2"] == 0.5
    assert metadata["training"]["command"] == "swarm-sim train --dataset smoke"
    assert metadata["architecture"]["parameters"] == count_parameters(model)
    assert metadata["architecture"]["arch"] == "dronet"
    assert metadata["torch_version"] == torch.__version__
    assert "enable_onednn_fusion" in metadata["runtime"]["onednn_fusion"]
    assert metadata["eager_weights"]["file"] == weights_path_for(result.path).name


def test_a_file_that_does_not_match_its_hash_is_refused(exported, tmp_path) -> None:
    _, result, _ = exported
    for suffix in (".pt", ".json", ".weights.pt"):
        source = result.path.with_name(result.path.stem + suffix)
        (tmp_path / f"policy{suffix}").write_bytes(source.read_bytes())
    tampered = tmp_path / "policy.pt"
    data = bytearray(tampered.read_bytes())
    data[len(data) // 2] ^= 0xFF
    tampered.write_bytes(bytes(data))
    with pytest.raises(ModelError, match="refused"):
        load_model(tampered)
    with pytest.raises(ModelError, match="refused"):
        load_eager_model(tampered)
    assert main(["evaluate", "--model", str(tampered), "--dataset", "unused"]) == 2


@pytest.mark.parametrize("fusion", [True, False])
def test_the_export_records_a_reference_the_drone_loader_reproduces(exported, fusion) -> None:
    _, result, _ = exported
    recorded = load_model(result.path).reference
    assert recorded is not None and recorded.made_with is not None
    assert recorded.output_body_flu_mps == result.reference.output_body_flu_mps
    assert recorded.made_with["torch"] == torch.__version__
    np.testing.assert_array_equal(recorded.image_u8, result.reference.image_u8)
    fusion_before = torch.jit.onednn_fusion_enabled()
    try:
        with Policy.load(PolicyConfig(model_path=result.path, graph_fusion=fusion)) as policy:
            assert policy.reference_error_mps is not None
            assert policy.reference_error_mps < 1e-5
    finally:
        enable_graph_fusion(fusion_before)


def test_add_reference_to_a_policy_exported_before_the_check(exported, tmp_path) -> None:
    _, result, _ = exported
    for suffix in (".pt", ".json", ".weights.pt"):
        source = result.path.with_name(result.path.stem + suffix)
        (tmp_path / f"policy{suffix}").write_bytes(source.read_bytes())
    old = tmp_path / "policy.pt"
    record = json.loads(sidecar_path(old).read_text())
    del record["reference"]  # as an export made before the platform check wrote it
    sidecar_path(old).write_text(json.dumps(record))
    assert load_model(old).reference is None
    added = add_reference(old, "test")
    again = json.loads(sidecar_path(old).read_text())
    assert again["sha256"] == record["sha256"] and again["metadata"] == record["metadata"]
    # Recomputed from the file, maybe with another thread count: float32 sums reordered.
    np.testing.assert_allclose(
        added.output_body_flu_mps, result.reference.output_body_flu_mps, atol=1e-5, rtol=0
    )
    with Policy.load(PolicyConfig(model_path=old, graph_fusion=False)) as policy:
        assert policy.reference_error_mps is not None and policy.reference_error_mps < 1e-5


def test_tampered_eager_weights_are_refused(exported, tmp_path) -> None:
    _, result, _ = exported
    for suffix in (".pt", ".json", ".weights.pt"):
        source = result.path.with_name(result.path.stem + suffix)
        (tmp_path / f"policy{suffix}").write_bytes(source.read_bytes())
    weights = tmp_path / "policy.weights.pt"
    data = bytearray(weights.read_bytes())
    data[len(data) // 2] ^= 0xFF
    weights.write_bytes(bytes(data))
    load_model(tmp_path / "policy.pt")  # the policy itself is intact
    with pytest.raises(ModelError, match="weights.pt does not match"):
        load_eager_model(tmp_path / "policy.pt")


def test_eager_weights_rebuild_the_network(exported) -> None:
    model, result, _ = exported
    rebuilt, metadata = load_eager_model(result.path)
    assert metadata["dataset"]["id"] == result.metadata["dataset"]["id"]
    images = torch.randint(0, 256, (3, 64, 384), dtype=torch.uint8)
    with torch.inference_mode():
        assert torch.equal(rebuilt(images), model(images))


def test_swarm_sim_export_from_a_training_run(smoke_dataset, tmp_path, capsys) -> None:
    run = tmp_path / "run"
    config = TrainConfig(
        dataset=smoke_dataset, out_dir=run, max_epochs=1, limit_train=16, progress=False
    )
    train(config)
    out = tmp_path / "models" / "p.pt"
    evaluation = tmp_path / "eval"
    args = ["export", "--checkpoint", str(run), "--dataset", str(smoke_dataset)]
    assert main([*args, "--out", str(out), "--eval-out", str(evaluation)]) == 0
    assert "test n = 180" in capsys.readouterr().out
    metadata = load_model(out).metadata
    report = json.loads((evaluation / "metrics.json").read_text())
    assert metadata["test_metrics"]["metrics"] == report["metrics"]
    assert metadata["test_metrics"]["split"] == "test"
    assert metadata["training"]["epochs_run"] == 1
    assert metadata["training"]["chain"] == [config.command]  # trained from scratch: all of it
    assert metadata["training"]["chain_complete"] is True
    assert metadata["export_check"]["max_abs_diff_mps"] <= 1e-5
    assert weights_path_for(out).exists()


def _sidecar(path, training) -> str:
    path.with_suffix(".json").write_text(json.dumps({"metadata": {"training": training}}))
    return str(path)


def test_a_fine_tune_records_the_whole_chain_of_training_commands(tmp_path) -> None:
    base = _sidecar(tmp_path / "base.pt", {"command": "train A", "config": {"init_from": None}})
    first = training_chain("train B --init-from base.pt", base)
    assert first == {"chain": ["train A", "train B --init-from base.pt"], "chain_complete": True}
    tuned = _sidecar(tmp_path / "tuned.pt", {"command": "train B", **first})
    assert training_chain("train C", tuned)["chain"] == [*first["chain"], "train C"]
    # An ancestor that recorded only its own (fine-tuning) command, or none that can be read.
    older = _sidecar(tmp_path / "old.pt", {"command": "train X", "config": {"init_from": "m.pt"}})
    assert training_chain("train Y", older) == {
        "chain": ["train X", "train Y"],
        "chain_complete": False,
    }
    missing = training_chain("train Z", str(tmp_path / "gone.pt"))
    assert missing == {"chain": ["train Z"], "chain_complete": False}


def test_a_chain_is_the_one_recorded_when_the_fine_tune_started(smoke_dataset, tmp_path) -> None:
    # Round B is tuned from the shipped file, then shipped over it: exporting B again (or any
    # descendant) must not read B's own history through the overwritten path.
    shipped = tmp_path / "models" / "p.pt"

    def run(name: str, init_from=None):
        config = TrainConfig(
            dataset=smoke_dataset,
            out_dir=tmp_path / name,
            max_epochs=1,
            limit_train=16,
            progress=False,
            command=f"train {name}",
            init_from=init_from,
        )
        train(config)
        return config.out_dir

    def export(run_dir, out) -> list[str]:
        args = ["export", "--checkpoint", str(run_dir), "--dataset", str(smoke_dataset)]
        assert main([*args, "--out", str(out), "--eval-out", str(tmp_path / "eval")]) == 0
        return load_model(out).metadata["training"]["chain"]

    assert export(run("A"), shipped) == ["train A"]
    b = run("B", init_from=shipped)
    assert export(b, shipped) == ["train A", "train B"]  # B shipped over A
    assert export(b, tmp_path / "again.pt") == ["train A", "train B"]
    c = run("C", init_from=b / "last.ckpt")
    assert export(c, tmp_path / "c.pt") == ["train A", "train B", "train C"]


def test_an_output_gain_scales_every_answer_and_is_recorded(smoke_dataset, tmp_path) -> None:
    run = tmp_path / "run"
    config = TrainConfig(
        dataset=smoke_dataset, out_dir=run, max_epochs=1, limit_train=16, progress=False
    )
    train(config)

    def export(name: str, *extra: str):
        out = tmp_path / f"{name}.pt"
        args = ["export", "--checkpoint", str(run), "--dataset", str(smoke_dataset)]
        assert main([*args, "--out", str(out), "--eval-out", str(tmp_path / name), *extra]) == 0
        return load_model(out)

    symmetric = export("symmetric", "--symmetry", "c4")
    gained = export("gained", "--output-gain", "1.25", "--symmetry", "c4")
    assert symmetric.metadata["training"]["output_gain"] == 1.0
    assert gained.metadata["training"]["output_gain"] == 1.25
    images = torch.from_numpy(open_dataset(smoke_dataset).split("test").images[:8].copy())
    with torch.inference_mode():
        base = symmetric.module(images)
        scaled = gained.module(images)
    assert float(base.abs().max()) > 0.01  # the network answers something to scale
    torch.testing.assert_close(scaled, 1.25 * base, rtol=1e-4, atol=1e-5)
    # The eager weights Grad-CAM reads carry the same gain.
    eager, _ = load_eager_model(tmp_path / "gained.pt")
    with torch.inference_mode():
        torch.testing.assert_close(
            eager(images[:2]),
            1.25 * load_eager_model(tmp_path / "symmetric.pt")[0](images[:2]),
            rtol=1e-4,
            atol=1e-5,
        )


@pytest.mark.parametrize("gain", ["0", "-1", "2.5", "nan"])
def test_an_output_gain_out_of_range_is_refused_naming_the_field(
    smoke_dataset, tmp_path, gain, capsys
) -> None:
    args = ["export", "--checkpoint", str(tmp_path / "none.ckpt"), "--dataset", str(smoke_dataset)]
    status = main([*args, "--out", str(tmp_path / "p.pt"), "--output-gain", gain])
    assert status != 0
    assert "output-gain" in capsys.readouterr().err
