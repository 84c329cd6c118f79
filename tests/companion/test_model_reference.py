"""The platform check at load: a policy must reproduce the reference output recorded at export.

Real TorchScript files (tests/companion/conftest.py) with a reference written into their sidecar
as an export writes it; `Policy.load` runs the warmed-up policy on the reference image, fused and
unfused, and refuses a mismatch with one line naming the error and the tolerance.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.errors import ModelError
from companion.model_file import load_model, sidecar_path
from companion.model_reference import (
    DEFAULT_TOLERANCE_MPS,
    SIDECAR_KEY,
    Reference,
    reference_from_json,
    reference_scene,
)
from companion.policy import Policy, PolicyConfig, error_line

SCENE = reference_scene()
BRIGHTNESS = float(SCENE.astype(np.float32).mean() / 255.0)  # the "brightness" model's x output


def brightness_output(offset_x_mps: float = 0.0) -> tuple[float, float, float]:
    return (BRIGHTNESS + offset_x_mps, -BRIGHTNESS, 0.0)


def with_reference(path: Path, **reference: Any) -> Path:
    """Write a reference into `path`'s sidecar (JSON fields override the valid default)."""
    record = json.loads(sidecar_path(path).read_text())
    record[SIDECAR_KEY] = {**Reference(SCENE, brightness_output()).to_json(), **reference}
    sidecar_path(path).write_text(json.dumps(record))
    return path


def load(path: Path, graph_fusion: bool = False) -> Policy:
    return Policy.load(PolicyConfig(model_path=path, graph_fusion=graph_fusion))


@pytest.mark.parametrize("graph_fusion", [False, True], ids=["unfused", "fused"])
def test_a_policy_that_reproduces_its_reference_loads(make_policy_file, graph_fusion) -> None:
    path = with_reference(make_policy_file("brightness"))
    with load(path, graph_fusion) as policy:
        assert policy.reference_error_mps is not None and policy.reference_error_mps < 1e-6
        assert "reference output within" in policy.reference_text


@pytest.mark.parametrize(
    ("offset_mps", "refused"),
    [
        (8.9, True),  # the fault seen under an emulated 512-bit SVE CPU
        (1.1 * DEFAULT_TOLERANCE_MPS, True),  # just outside the tolerance
        (0.9 * DEFAULT_TOLERANCE_MPS, False),  # just inside
    ],
)
def test_a_wrong_reference_output_is_refused_in_one_line(
    make_policy_file, offset_mps: float, refused: bool
) -> None:
    path = with_reference(
        make_policy_file("brightness"), output_body_flu_mps=list(brightness_output(offset_mps))
    )
    if not refused:
        with load(path) as policy:
            assert policy.reference_error_mps == pytest.approx(offset_mps, rel=1e-3)
        return
    with pytest.raises(ModelError) as caught:
        load(path)
    message = str(caught.value)
    assert "\n" not in message
    assert f"max error {offset_mps:.3g} m/s exceeds the tolerance 0.001 m/s" in message
    assert "reference input" in message and message.endswith("refused")


def test_a_policy_exported_before_the_check_loads_with_a_warning(
    make_policy_file, caplog: pytest.LogCaptureFixture
) -> None:
    path = make_policy_file("brightness")  # save_model without a reference: an older export
    assert load_model(path).reference is None
    with caplog.at_level(logging.WARNING, logger="companion.policy"), load(path) as policy:
        assert policy.reference_error_mps is None
        assert "no reference output to check" in policy.reference_text
    assert any("has no reference output" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    ("field", "value", "named"),
    [
        ("tolerance_mps", 0.5, "reference.tolerance_mps: expected a number in (0, 0.01] m/s"),
        ("tolerance_mps", 0.0, "reference.tolerance_mps"),
        ("output_body_flu_mps", [1.0, 2.0], "reference.output_body_flu_mps: expected 3 finite"),
        ("output_body_flu_mps", [1.0, 2.0, float("nan")], "reference.output_body_flu_mps"),
        ("image_png_base64", "not base64!", "reference.image_png_base64: expected base64 PNG"),
        ("image_png_base64", "AAAA", "reference.image_png_base64: expected an 8-bit grey 384x64"),
    ],
)
def test_a_malformed_reference_is_refused_naming_the_field(
    make_policy_file, field: str, value: Any, named: str
) -> None:
    path = with_reference(make_policy_file("brightness"), **{field: value})
    with pytest.raises(ModelError, match="reference") as caught:
        load(path)
    assert named in str(caught.value)


def test_the_reference_image_travels_exactly_as_png() -> None:
    reference = Reference(SCENE, (1.0, -2.0, 0.5), made_with={"how": "test"})
    back = reference_from_json(json.loads(json.dumps(reference.to_json())), "x.json")
    np.testing.assert_array_equal(back.image_u8, SCENE)
    assert back.output_body_flu_mps == (1.0, -2.0, 0.5)
    assert back.tolerance_mps == DEFAULT_TOLERANCE_MPS and back.made_with == {"how": "test"}
    # The scene is about what the cameras see (not saturated noise): sky, ground and drones.
    assert SCENE.shape == (64, 384) and 100 < SCENE.mean() < 200 and SCENE.min() < 70


def test_a_model_that_fails_at_warm_up_is_refused_in_one_line(tmp_path: Path) -> None:
    """Valid hash and metadata, but the first call fails (a layer of the wrong size)."""
    import torch
    from torch import Tensor, nn

    from companion.model_file import base_metadata, save_model, torchscript_calls

    class WrongInput(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.head = nn.Linear(10, 3)

        def forward(self, images: Tensor) -> Tensor:
            return self.head(images.to(torch.float32).reshape(images.shape[0], -1))

    path = tmp_path / "wrong_input.pt"
    with torchscript_calls():
        save_model(torch.jit.script(WrongInput().eval()), base_metadata(), path)
    with pytest.raises(ModelError) as caught:
        load(path)
    message = str(caught.value)
    assert "\n" not in message
    assert message == (
        f"model {path} failed at warm-up: RuntimeError: mat1 and mat2 shapes cannot be "
        "multiplied (1x24576 and 10x3): refused"
    )


def test_error_line_picks_the_original_error_of_a_torchscript_traceback() -> None:
    scripted = RuntimeError(
        "The following operation failed in the TorchScript interpreter.\n"
        "Traceback of TorchScript (most recent call last):\n"
        '  File "m.py", line 7, in forward\n'
        "    return F.linear(input, self.weight, self.bias)\n"
        "           ~~~~~~~~ <--- HERE\n"
        "RuntimeError: mat1 and mat2 shapes cannot be multiplied (1x24576 and 10x3)\n"
    )
    assert error_line(scripted) == (
        "RuntimeError: mat1 and mat2 shapes cannot be multiplied (1x24576 and 10x3)"
    )
    native = RuntimeError("bad alloc\nException raised from f at x.cpp:1 (most recent call first):")
    assert error_line(native) == "RuntimeError: bad alloc"
    assert error_line(ValueError("")) == "ValueError"
