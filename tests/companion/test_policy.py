"""Policy: real TorchScript files loaded and verified, inference off the loop, outputs checked."""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from companion.errors import ConfigError, ModelError
from companion.model_file import (
    METADATA_NAME,
    base_metadata,
    sha256_file,
    sidecar_path,
    torchscript_calls,
)
from companion.policy import Policy, PolicyConfig, PolicyOutput

IMAGE = np.full((64, 384), 51, dtype=np.uint8)  # brightness 0.2


def load(path: Path, **kwargs: object) -> Policy:
    return Policy.load(PolicyConfig(model_path=path, **kwargs))  # type: ignore[arg-type]


def infer(policy: Policy, image: np.ndarray = IMAGE) -> PolicyOutput:
    return asyncio.run(policy.infer(image))


class GatedPolicy(Policy):
    """A real policy whose model call waits for `gate` first: a model that hangs on demand."""

    gate: threading.Event
    started: threading.Event

    def _run_model(self, batch_u8: torch.Tensor) -> torch.Tensor:
        if batch_u8.shape[0] == 1 and int(batch_u8[0, 0, 0]) == 99:
            self.started.set()
            self.gate.wait(timeout=30.0)
        return super()._run_model(batch_u8)


def test_loads_real_file_and_infers_from_the_image(make_policy_file) -> None:
    path = make_policy_file("brightness")
    with load(path, sha256=sha256_file(path)) as policy:
        assert policy.sha256 == sha256_file(path)
        assert policy.metadata["output"]["frame"] == "body_flu"
        assert policy.warmup_latency_s is not None and policy.warmup_latency_s > 0
        out = infer(policy)
        assert out.ok and out.reason == ""
        np.testing.assert_allclose(out.vel_body_flu, [0.2, -0.2, 0.0], atol=1e-6)
        assert out.vel_body_flu.shape == (3,) and out.latency_s >= 0.0
        assert policy.in_flight_since is None
        assert out.as_dict()["vel_body_flu"] == pytest.approx([0.2, -0.2, 0.0], abs=1e-6)


def test_refuses_a_wrong_hash(make_policy_file) -> None:
    path = make_policy_file("constant")
    with pytest.raises(ModelError, match="refused"):
        load(path, sha256="0" * 64)


def test_refuses_a_tampered_file(make_policy_file) -> None:
    path = make_policy_file("constant")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ModelError, match="records"):
        load(path)


def test_refuses_metadata_of_another_frame(tmp_path: Path, make_policy_file) -> None:
    # Written by hand (save_model itself refuses such metadata): body FRD output.
    source = make_policy_file("constant")
    metadata = base_metadata()
    metadata["output"]["frame"] = "body_frd"
    path = tmp_path / "frd.pt"
    with torchscript_calls():
        module = torch.jit.load(str(source))
        torch.jit.save(module, str(path), _extra_files={METADATA_NAME: json.dumps(metadata)})
    sidecar_path(path).write_text(json.dumps({"sha256": sha256_file(path), "metadata": metadata}))
    with pytest.raises(ModelError, match="output.frame"):
        load(path)


@pytest.mark.parametrize(
    ("kind", "value", "reason"),
    [
        ("nan", (0.0, 0.0, 0.0), "non-finite"),
        ("constant", (30.0, 0.0, 0.0), "exceeds the bound 10 m/s"),
        ("wide", (0.0, 0.0, 0.0), "output shape (4,)"),
    ],
)
def test_bad_outputs_are_refused_not_raised(make_policy_file, kind, value, reason) -> None:
    with load(make_policy_file(kind, value)) as policy:
        out = infer(policy)
        assert not out.ok
        assert reason in out.reason
        np.testing.assert_array_equal(out.vel_body_flu, np.zeros(3))
        assert policy.in_flight_since is None


def test_model_exception_is_reported_and_the_next_call_works(make_policy_file) -> None:
    with load(make_policy_file("raise")) as policy:
        failing = np.full((64, 384), 255, dtype=np.uint8)

        async def run() -> tuple[PolicyOutput, PolicyOutput]:
            return await policy.infer(failing), await policy.infer(IMAGE)

        bad, good = asyncio.run(run())
        assert not bad.ok and "model error" in bad.reason and "synthetic" in bad.reason
        assert good.ok


def test_wrong_input_is_refused(make_policy_file) -> None:
    with load(make_policy_file("constant")) as policy:
        assert "uint8" in infer(policy, np.zeros((64, 384), dtype=np.float32)).reason
        assert not infer(policy, np.zeros((64, 64), dtype=np.uint8)).ok


def test_slow_model_runs_off_the_loop_with_in_flight_since_visible(make_policy_file) -> None:
    with load(make_policy_file("spin"), warmup_runs=0) as policy:
        image = np.zeros((64, 384), dtype=np.uint8)
        image[0, 0] = 3  # about 60k interpreted iterations: a few hundred ms

        async def run() -> tuple[PolicyOutput, int, list[float]]:
            task = asyncio.create_task(policy.infer(image))
            await asyncio.sleep(0)
            seen: list[float] = []
            ticks = 0
            while not task.done():
                since = policy.in_flight_since
                if since is not None:
                    seen.append(since)
                ticks += 1
                await asyncio.sleep(0.002)
            return await task, ticks, seen

        out, ticks, seen = asyncio.run(run())
        assert out.ok
        np.testing.assert_allclose(out.vel_body_flu, [0.5, 0.0, 0.0])
        assert ticks > 1  # the event loop kept running while the model ran
        assert seen and len(set(seen)) == 1  # one start time, visible the whole time
        assert policy.in_flight_since is None


def test_hung_model_makes_calls_busy_and_survives_cancellation(make_policy_file) -> None:
    path = make_policy_file("constant")
    policy = GatedPolicy.load(PolicyConfig(model_path=path), clock=lambda: 100.0)
    policy.gate, policy.started = threading.Event(), threading.Event()
    hang = np.full((64, 384), 99, dtype=np.uint8)

    async def run() -> None:
        stuck = asyncio.create_task(policy.infer(hang))
        await asyncio.sleep(0)
        assert policy.in_flight_since == 100.0
        await asyncio.to_thread(policy.started.wait, 10.0)  # the model is running now
        busy = await policy.infer(IMAGE)
        assert not busy.ok and busy.reason.startswith("busy")
        stuck.cancel()  # the daemon gives up waiting; the model keeps running
        with pytest.raises(asyncio.CancelledError):
            await stuck
        assert policy.in_flight_since == 100.0
        policy.gate.set()
        while policy.in_flight_since is not None:
            await asyncio.sleep(0.01)
        assert (await policy.infer(IMAGE)).ok

    try:
        asyncio.run(run())
    finally:
        policy.gate.set()
        policy.close()


def test_close_does_not_wait_forever_for_a_hung_model(make_policy_file) -> None:
    policy = GatedPolicy.load(PolicyConfig(model_path=make_policy_file("constant")))
    policy.gate, policy.started = threading.Event(), threading.Event()

    async def start_hang() -> None:
        task = asyncio.create_task(policy.infer(np.full((64, 384), 99, dtype=np.uint8)))
        await asyncio.to_thread(policy.started.wait, 10.0)
        task.cancel()

    asyncio.run(start_hang())
    assert policy.in_flight_since is not None
    policy.close(timeout_s=0.1)  # returns although the model is still stuck
    out = infer(policy)
    assert not out.ok
    policy.gate.set()


def test_infer_batch_matches_and_zeroes_invalid_rows(make_policy_file) -> None:
    images = np.stack([np.full((64, 384), v, dtype=np.uint8) for v in (0, 51, 255)])
    with load(make_policy_file("brightness")) as policy:
        out = policy.infer_batch(images)
        assert out.shape == (3, 3) and out.dtype == np.float64
        np.testing.assert_allclose(out[:, 0], [0.0, 0.2, 1.0], atol=1e-6)
        with pytest.raises(ValueError, match="uint8"):
            policy.infer_batch(images[0])
    with load(make_policy_file("nan")) as policy:
        np.testing.assert_array_equal(policy.infer_batch(images), np.zeros((3, 3)))
        assert np.all(np.isnan(policy.infer_batch(images, zero_invalid=False)))


def test_config_validation_and_from_dict(tmp_path: Path) -> None:
    cfg = PolicyConfig.from_dict({"model_path": "models/p.pt", "threads": 2}, base_dir=tmp_path)
    assert cfg.model_path == tmp_path / "models" / "p.pt" and cfg.threads == 2
    assert (cfg.max_speed_mps, cfg.warmup_runs, cfg.sha256) == (10.0, 3, None)
    assert cfg.graph_fusion is True
    with pytest.raises(ConfigError, match="policy.graph_fusion: expected true or false, got 'no'"):
        PolicyConfig(model_path="p.pt", graph_fusion="no")  # type: ignore[arg-type]
    assert PolicyConfig(model_path="p.pt", sha256="AB" * 32).sha256 == "ab" * 32
    with pytest.raises(ConfigError, match=r"unknown key\(s\) 'path'"):
        PolicyConfig.from_dict({"path": "x.pt"})
    with pytest.raises(ConfigError, match="policy.model_path: missing"):
        PolicyConfig.from_dict({})
    with pytest.raises(ConfigError, match="policy.sha256: expected 64 hex digits"):
        PolicyConfig(model_path="p.pt", sha256="abc")
    with pytest.raises(ConfigError, match=r"policy.threads: 0 is outside the allowed range \[1"):
        PolicyConfig(model_path="p.pt", threads=0)
    with pytest.raises(ConfigError, match="policy.max_speed_mps"):
        PolicyConfig(model_path="p.pt", max_speed_mps=float("inf"))
