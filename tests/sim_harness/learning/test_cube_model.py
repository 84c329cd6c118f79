"""The cube network: faces padded by their true neighbours, DroNet's weights, export, training."""

import asyncio
import math

import numpy as np
import pytest
import torch

from companion.camera.layout import FACE_NAMES, FACES, FOV_DEG
from companion.errors import ConfigError
from companion.model_file import enable_graph_fusion, load_model
from companion.policy import Policy, PolicyConfig
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.checkpoint import (
    LAST_NAME,
    CheckpointError,
    load_checkpoint,
    model_from_checkpoint,
)
from sim_harness.learning.export import export_policy, load_eager_model
from sim_harness.learning.gradcam import grad_cam
from sim_harness.learning.model import (
    CubeDroNet,
    CubePad,
    DroNet,
    build_model,
    cube_pad_index,
    faces_to_strip,
    strip_to_faces,
)
from sim_harness.learning.symmetry import SymmetricPolicy
from sim_harness.learning.train import TrainConfig, train

FRONT, UP = FACE_NAMES.index("front"), FACE_NAMES.index("up")


def cell_rays(size: int, pad: int) -> np.ndarray:
    """Unit ray of every cell of the padded faces, (6, size + 2 pad, size + 2 pad, 3)."""
    half = math.tan(math.radians(FOV_DEG) / 2)
    coords = ((np.arange(-pad, size + pad) + 0.5) / size * 2 - 1) * half
    rays = []
    for face in FACES:
        right, up, axis = (
            np.array(v) for v in (face.right_body_flu, face.up_body_flu, face.axis_body_flu)
        )
        ray = coords[None, :, None] * right + coords[::-1][:, None, None] * up + axis
        rays.append(ray / np.linalg.norm(ray, axis=-1, keepdims=True))
    return np.stack(rays)


@pytest.mark.parametrize(("size", "pad"), [(64, 2), (32, 1), (4, 1), (2, 1)])
def test_each_padding_cell_comes_from_the_cell_that_looks_the_same_way(size, pad) -> None:
    index = cube_pad_index(size, pad).numpy().reshape(6, size + 2 * pad, size + 2 * pad)
    inner = index[:, pad : pad + size, pad : pad + size]
    assert (inner.ravel() == np.arange(6 * size * size)).all()  # a face is itself
    padded_rays = cell_rays(size, pad)
    source_rays = cell_rays(size, 0).reshape(-1, 3)[index]
    angle = np.degrees(np.arccos(np.clip((padded_rays * source_rays).sum(-1), -1.0, 1.0)))
    cell_deg = FOV_DEG / size
    # nearest cell of the face that sees the direction best: within one cell's diagonal
    assert angle.max() <= math.sqrt(2) * cell_deg + 1e-6
    ring = np.ones(index.shape[1:], bool)
    ring[pad : pad + size, pad : pad + size] = False
    assert (index[:, ring] // (size * size) != np.arange(6)[:, None]).all()  # from other faces


@pytest.mark.parametrize(("size", "pad"), [(64, 2), (16, 1), (2, 1)])
def test_cube_pad_is_the_gather_of_its_index_values_and_gradients(size, pad) -> None:
    # CubePad copies the middle and gathers only the border, with its own backward: it must
    # equal the plain whole-frame gather of `cube_pad_index`, autograd's gradient included,
    # when training, under no_grad and for a non-channels_last input.
    torch.manual_seed(size)
    padded = size + 2 * pad
    x = torch.randn(12, 3, size, size, dtype=torch.float64)
    x = x.contiguous(memory_format=torch.channels_last).requires_grad_()
    flat = x.permute(0, 2, 3, 1).reshape(2, 6 * size * size, 3)
    gathered = torch.index_select(flat, 1, cube_pad_index(size, pad))
    expected = gathered.reshape(12, padded, padded, 3).permute(0, 3, 1, 2)
    out = CubePad(size, pad)(x)
    assert out.is_contiguous(memory_format=torch.channels_last)
    weights = torch.randn_like(out)
    (grad,) = torch.autograd.grad((out * weights).sum(), x)
    (grad_expected,) = torch.autograd.grad((expected * weights).sum(), x)
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    torch.testing.assert_close(grad, grad_expected)
    with torch.no_grad():
        torch.testing.assert_close(CubePad(size, pad)(x), expected, rtol=0, atol=0)
        torch.testing.assert_close(CubePad(size, pad)(x.contiguous()), expected, rtol=0, atol=0)
    if size <= 4:
        assert torch.autograd.gradcheck(CubePad(size, pad), (x.detach().requires_grad_(),))


def test_the_front_face_top_edge_sees_the_up_face_and_dronet_does_not() -> None:
    # A bright patch on the up face just above the front camera's view (the faces overlap by
    # 10 deg, so the directions just beyond the front tile's top edge are the up tile's rows
    # 53-54, not its last rows): only the cube network's first conv, at the front face's top
    # row, responds to it.
    torch.manual_seed(0)
    plain = build_model(128.0, 64.0).eval()
    cube = build_model(128.0, 64.0, arch="cube").eval()
    cube.load_state_dict(plain.state_dict())
    image = torch.full((1, 64, 384), 128, dtype=torch.uint8)
    lit = image.clone()
    lit[0, 50:58, UP * 64 + 20 : UP * 64 + 44] = 255
    outputs = {}
    for name, model in (("dronet", plain), ("cube", cube)):
        with torch.no_grad():
            pair = []
            for img in (image, lit):
                if name == "cube":
                    pair.append(
                        faces_to_strip(
                            model.conv1(model.pad_conv1(strip_to_faces(model.standardize(img))))
                        )
                    )
                else:
                    pair.append(model.conv1(model.standardize(img)))
        outputs[name] = (pair[1] - pair[0]).abs()[0, :, 0, FRONT * 32 : FRONT * 32 + 32]
    assert outputs["dronet"].max() == 0.0
    assert outputs["cube"].max() > 0.1


def test_same_weights_either_way_and_the_cube_network_runs_on_the_strip() -> None:
    torch.manual_seed(1)
    plain = build_model(150.0, 40.0)
    cube = build_model(150.0, 40.0, arch="cube")
    assert isinstance(cube, CubeDroNet) and cube.arch == "cube" and plain.arch == "dronet"
    assert list(plain.state_dict()) == list(cube.state_dict())
    cube.load_state_dict(plain.state_dict())
    plain.load_state_dict(cube.state_dict())
    images = torch.randint(0, 256, (3, 64, 384), dtype=torch.uint8)
    with torch.no_grad():
        out = cube.eval()(images)
    assert out.shape == (3, 3) and (out == 0).all()  # zero head, as DroNet's
    faces = strip_to_faces(images[:, None].float())
    assert faces.shape == (18, 1, 64, 64) and torch.equal(
        faces_to_strip(faces)[:, 0], images.float()
    )


def test_an_unknown_architecture_names_the_field() -> None:
    with pytest.raises(ConfigError, match="arch: unknown architecture 'resnet'.*dronet, cube"):
        build_model(128.0, 64.0, arch="resnet")
    with pytest.raises(ConfigError, match="arch"):
        TrainConfig(dataset=".", out_dir=".", arch="resnet")  # type: ignore[arg-type]


def looks_trained(model: DroNet, images: torch.Tensor) -> DroNet:
    """Batch-norm statistics from real images and a head giving about 1 m/s."""
    generator = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.reset_running_stats()
                module.momentum = None
        model.train()
        model(images)
        model.head.weight.copy_(torch.randn(3, 3072, generator=generator) * 0.01)
        model.head.bias.copy_(torch.tensor([0.1, -0.2, 0.05]))
    return model.eval()


def test_a_cube_policy_exports_reloads_and_explains(smoke_dataset, tmp_path) -> None:
    dataset = open_dataset(smoke_dataset)
    images = torch.from_numpy(np.array(dataset.split("train").images[:64]))
    torch.manual_seed(3)
    model = looks_trained(build_model(185.0, 36.0, arch="cube"), images)
    result = export_policy(
        model, tmp_path / "cube.pt", dataset.manifest, None, {"command": "test"}, symmetry="d4"
    )
    assert result.max_abs_diff_mps <= 1e-5
    eager, _ = load_eager_model(result.path)
    assert isinstance(eager, CubeDroNet)
    loaded = load_model(result.path)
    frozen = loaded.module
    # the file says which network it carries, and claims no standardization folded into conv1
    assert loaded.metadata["architecture"]["arch"] == "cube"
    assert "folded" not in loaded.metadata["runtime"]["graph"]
    with torch.inference_mode():
        eager_out = SymmetricPolicy(eager, "d4")(images[:9])
        frozen_out = frozen(images[:9])
    assert 0.05 < eager_out.abs().max() < 10.0
    assert (frozen_out - eager_out).abs().max() <= 1e-5
    saliency = grad_cam(eager, images[:2].numpy())
    assert saliency.cam.shape == (2, 4, 24) and saliency.heatmap.shape == (2, 64, 384)
    assert np.isfinite(saliency.heatmap).all() and saliency.heatmap.max() == pytest.approx(1.0)


def test_training_a_cube_network_from_dronet_weights(smoke_dataset, tmp_path) -> None:
    base = dict(batch_size=32, limit_train=64, limit_val=32, progress=False, max_epochs=1)
    train(TrainConfig(dataset=smoke_dataset, out_dir=tmp_path / "plain", **base))
    config = TrainConfig(
        dataset=smoke_dataset,
        out_dir=tmp_path / "cube",
        arch="cube",
        init_from=tmp_path / "plain" / LAST_NAME,
        **base,
    )
    result = train(config)
    state = load_checkpoint(tmp_path / "cube" / LAST_NAME)
    assert state["model_config"]["arch"] == "cube"
    assert np.isfinite(result.history[-1]["val_loss"])
    model = model_from_checkpoint(state)
    assert isinstance(model, CubeDroNet)
    with pytest.raises(CheckpointError, match="trains arch cube, not dronet"):
        train(TrainConfig(dataset=smoke_dataset, out_dir=tmp_path / "cube", resume=True, **base))
    plain = load_checkpoint(tmp_path / "plain" / LAST_NAME)
    assert plain["model_config"]["arch"] == "dronet"
    del plain["model_config"]["arch"]  # a checkpoint from before the option
    assert type(model_from_checkpoint(plain)) is DroNet


@pytest.mark.parametrize("fusion", [True, False])
def test_the_drone_loader_runs_a_cube_policy(smoke_dataset, tmp_path, fusion) -> None:
    dataset = open_dataset(smoke_dataset)
    images = np.array(dataset.split("train").images[:9])
    torch.manual_seed(4)
    model = looks_trained(build_model(185.0, 36.0, arch="cube"), torch.from_numpy(images))
    path = export_policy(model, tmp_path / "c.pt", dataset.manifest, None, {"command": "t"}).path
    with torch.inference_mode():
        expected = model(torch.from_numpy(images)).numpy()
    fusion_before = torch.jit.onednn_fusion_enabled()
    try:
        with Policy.load(PolicyConfig(model_path=path, graph_fusion=fusion)) as policy:
            one = asyncio.run(policy.infer(images[0]))
            batch = policy.infer_batch(images)
    finally:
        enable_graph_fusion(fusion_before)
    assert one.ok
    np.testing.assert_allclose(one.vel_body_flu, expected[0], atol=1e-5, rtol=0)
    np.testing.assert_allclose(batch, expected, atol=1e-5, rtol=0)
