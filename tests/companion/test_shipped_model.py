"""The shipped policy file, `models/swarm_cnn.pt`, pinned by its outputs (golden values).

A silent change of numerics (the file, torch, the loader, standardization, face order, graph
fusion) is a change of behaviour: the drone would fly differently. The file is loaded exactly as
the drone loads it (`Policy.load`, hash checked against its sidecar, warm-up), fused and unfused,
and run on fixed images, one by one through `infer` (the daemon's call, with its 10 m/s bound)
and as one batch (`infer_batch`, raw); the outputs must equal the recorded ones to
`TOLERANCE_MPS`. The images: uniform noise (far from what the cameras see), noise with about the
training images' pixel statistics, a constant gray, and a horizon with two dark drones. An output
over the daemon's 10 m/s bound must be refused by `infer` (the shipped model's are all below it).

Tolerance: 1e-4 m/s. Kernel choice (oneDNN's fused partitions vs the plain graph, batch 1 vs
batch 6, AVX2 vs AVX-512, thread count) reorders float32 sums: measured here, that moves these
outputs by at most 1.4e-6 m/s (the sidecar's export check: 5.8e-7 between the eager and the
exported model). A 1e-4 m/s velocity error integrates to 1 mm in 10 s of flight, below anything
the control law or PX4 resolves; a change that matters moves the outputs by far more (measured:
one grey level added to every pixel of an image, 7e-3 m/s with the model of 2026-11; the faces
rotated by one turn the answer by 90 degrees: the shipped policy averages over the rig's symmetric
views, `sim_harness.learning.symmetry`).

Regenerate the golden file (after shipping a new model on purpose) with
`.venv/bin/python tests/companion/test_shipped_model.py --regenerate`; it records the model's
hash and the torch version it was made with.
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from companion.camera.layout import IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.model_file import enable_graph_fusion, sha256_file, sidecar_path
from companion.policy import Policy, PolicyConfig

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "swarm_cnn.pt"
GOLDEN = Path(__file__).with_name("golden") / "shipped_model.json"
TOLERANCE_MPS = 1e-4
UNIFORM_SEEDS = (0, 1)
LIKE_TRAINING_SEEDS = (2, 3)
PIXEL_MEAN, PIXEL_STD = 185.0, 36.0  # about the training images' (sidecar: 184.8, 35.6)
GRAY = 128


def inputs() -> dict[str, np.ndarray]:
    """The fixed stitched images, each (64, 384) uint8, by name."""
    shape = (IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX)
    images = {
        f"uniform{seed}": np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
        for seed in UNIFORM_SEEDS
    }
    for seed in LIKE_TRAINING_SEEDS:
        noise = np.random.default_rng(seed).normal(PIXEL_MEAN, PIXEL_STD, shape)
        images[f"like_training{seed}"] = np.clip(np.round(noise), 0, 255).astype(np.uint8)
    images[f"gray{GRAY}"] = np.full(shape, GRAY, dtype=np.uint8)
    horizon = np.full(shape, 215, dtype=np.uint8)  # sky
    horizon[IMAGE_HEIGHT_PX // 2 :] = 140  # ground
    horizon[28:36, 28:36] = 40  # a drone straight ahead (front tile, columns 0-63)
    horizon[30:34, 220:224] = 40  # a smaller one, further away, in the left tile (192-255)
    images["horizon"] = horizon
    return images


def outputs(graph_fusion: bool) -> dict[str, list[float]]:
    """Raw body-FLU velocities (m/s) of the shipped model on `inputs()`, as one batch.

    Also runs each image through `infer`, the daemon's call: it must give the same velocity, or
    refuse it for being over the 10 m/s bound. Graph fusion and the thread count are
    process-wide: both are put back afterwards.
    """
    fusion_was = bool(torch.jit.onednn_fusion_enabled())  # type: ignore[no-untyped-call]
    threads = torch.get_num_threads()
    images = inputs()
    try:
        with Policy.load(PolicyConfig(model_path=MODEL, graph_fusion=graph_fusion)) as policy:
            # Fused exactly when asked and the build has oneDNN Graph (x86 torch has it).
            assert policy.fused is (graph_fusion and bool(torch.jit.onednn_fusion_enabled()))  # type: ignore[no-untyped-call]
            batch = policy.infer_batch(np.stack(list(images.values())), zero_invalid=False)
            raw = dict(zip(images, batch.tolist(), strict=True))

            async def one_by_one() -> None:
                for name, image in images.items():
                    out = await policy.infer(image)
                    if np.linalg.norm(raw[name]) > policy.config.max_speed_mps:
                        assert not out.ok and "exceeds the bound" in out.reason, name
                    else:
                        assert out.ok, (name, out.reason)
                        np.testing.assert_allclose(
                            out.vel_body_flu, raw[name], rtol=0, atol=TOLERANCE_MPS, err_msg=name
                        )

            asyncio.run(one_by_one())
            return raw
    finally:
        enable_graph_fusion(fusion_was)
        torch.set_num_threads(threads)


def test_the_shipped_model_matches_its_recorded_hash() -> None:
    recorded = json.loads(sidecar_path(MODEL).read_text())
    golden = json.loads(GOLDEN.read_text())
    assert sha256_file(MODEL) == recorded["sha256"] == golden["model_sha256"]


@pytest.mark.parametrize("graph_fusion", [False, True], ids=["unfused", "fused"])
def test_the_shipped_model_gives_its_recorded_outputs(graph_fusion: bool) -> None:
    golden = json.loads(GOLDEN.read_text())
    got = outputs(graph_fusion)
    assert got.keys() == golden["outputs"].keys()
    made_with = f"golden made with torch {golden['torch_version']}, running {torch.__version__}"
    for name, expected in golden["outputs"].items():
        np.testing.assert_allclose(
            got[name], expected, rtol=0, atol=TOLERANCE_MPS, err_msg=f"{name}: {made_with}"
        )
    # The images are different enough that the outputs are too: a model that ignored its
    # input (a constant) would not pass by matching constant golden values.
    values = np.array(list(golden["outputs"].values()))
    assert np.ptp(values, axis=0).max() > 100 * TOLERANCE_MPS


def quarter_turn(image: np.ndarray) -> np.ndarray:
    """The stitched image as the drone turned a quarter turn left sees it: front <- left, ..."""
    tiles = image.reshape(IMAGE_HEIGHT_PX, 6, IMAGE_HEIGHT_PX)
    turned = tiles[:, [3, 0, 1, 2, 4, 5], :].copy()
    turned[:, 4] = np.rot90(tiles[:, 4], 1)
    turned[:, 5] = np.rot90(tiles[:, 5], -1)
    return turned.reshape(image.shape)


def mirrored(image: np.ndarray) -> np.ndarray:
    """The stitched image of the scene mirrored in the body x-z plane: right and left faces
    swap, every face flipped left-right."""
    tiles = image.reshape(IMAGE_HEIGHT_PX, 6, IMAGE_HEIGHT_PX)
    return tiles[:, [0, 3, 2, 1, 4, 5], ::-1].copy().reshape(image.shape)


def test_the_shipped_model_is_the_symmetrized_policy_its_metadata_names() -> None:
    """The sidecar names the views the graph averages over: the rig's four quarter turns (c4),
    and with d4 each also mirrored (an ensemble's members each average over them). A constant
    image looks the same in every view, so such a policy's horizontal answer to it is exactly
    zero; a quarter turn of the faces turns its answer by a quarter turn; with d4, the mirrored
    scene gets the mirrored answer."""
    metadata = json.loads(sidecar_path(MODEL).read_text())["metadata"]
    symmetry = metadata["runtime"]["symmetry"]
    # an ensemble (`swarm-sim ensemble`) calls each member's own views
    members = [m["symmetry"] for m in metadata.get("ensemble", [])] or [symmetry["group"]]
    assert set(members) == {symmetry["group"]}
    assert (symmetry["group"], symmetry["views"] // len(members)) in (("c4", 4), ("d4", 8))
    golden = json.loads(GOLDEN.read_text())["outputs"]
    assert np.abs(golden[f"gray{GRAY}"][:2]).max() < 1e-6 < abs(golden[f"gray{GRAY}"][2])
    image = inputs()["horizon"]
    with Policy.load(PolicyConfig(model_path=MODEL)) as policy:
        out = policy.infer_batch(
            np.stack([image, quarter_turn(image), mirrored(image)]), zero_invalid=False
        )
    vx, vy, vz = out[0]
    np.testing.assert_allclose(out[1], [vy, -vx, vz], atol=TOLERANCE_MPS)
    if symmetry["group"] == "d4":
        np.testing.assert_allclose(out[2], [vx, -vy, vz], atol=TOLERANCE_MPS)
    else:  # c4 alone does not mirror: the horizon's drones are not placed symmetrically
        assert abs(out[2][1] + vy) > 100 * TOLERANCE_MPS


@pytest.mark.parametrize("graph_fusion", [False, True], ids=["unfused", "fused"])
def test_the_shipped_model_passes_its_platform_check(graph_fusion: bool) -> None:
    """The sidecar's reference (added by `sim_harness.learning.export.add_reference`, recorded in
    its `made_with`) is reproduced here far inside its 1e-3 m/s tolerance, fused and unfused."""
    fusion_was = bool(torch.jit.onednn_fusion_enabled())  # type: ignore[no-untyped-call]
    threads = torch.get_num_threads()
    try:
        with Policy.load(PolicyConfig(model_path=MODEL, graph_fusion=graph_fusion)) as policy:
            reference = policy.loaded.reference
            assert reference is not None and reference.tolerance_mps == 1e-3
            assert policy.reference_error_mps is not None
            # measured: 3e-8 m/s unfused, 1.5e-7 m/s fused
            assert policy.reference_error_mps < TOLERANCE_MPS
    finally:
        enable_graph_fusion(fusion_was)
        torch.set_num_threads(threads)


def regenerate() -> dict[str, Any]:
    """Write the golden file from the unfused model (the fused one is checked against it)."""
    doc = {
        "about": "outputs of models/swarm_cnn.pt on tests/companion/test_shipped_model.py's "
        "inputs(); regenerate with `python tests/companion/test_shipped_model.py --regenerate`",
        "model_sha256": sha256_file(MODEL),
        "torch_version": torch.__version__,
        "inputs": "inputs() in tests/companion/test_shipped_model.py",
        "units": "m/s, body FLU",
        "outputs": outputs(graph_fusion=False),
    }
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(doc, indent=1) + "\n")
    return doc


if __name__ == "__main__":
    if sys.argv[1:] != ["--regenerate"]:
        sys.exit(f"usage: {sys.argv[0]} --regenerate   (rewrites {GOLDEN})")
    print(json.dumps(regenerate()["outputs"], indent=1))
