"""Runs on a Ray cluster (a local instance, 2 CPUs, bound to 127.0.0.1): the same dataset byte for
byte as the local pool, a killed worker costs only its run, the same experiment results."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from sim_harness.dataset.generate import generate
from sim_harness.dataset.spec import SPLITS, DatasetSpec
from sim_harness.dataset.store import MANIFEST, run_path
from sim_harness.experiments.aggregate import AggregateConfig, aggregate
from sim_harness.experiments.runner import run_suite
from sim_harness.experiments.stats import experiment_table
from sim_harness.experiments.suites import SuiteConfig
from sim_harness.sim.executor import ClusterChoice

pytestmark = [
    pytest.mark.skipif(
        importlib.util.find_spec("ray") is None,
        reason="Ray is not installed: pip install -e '.[cluster]'",
    ),
    pytest.mark.slow,
]
LOCAL_RAY = ClusterChoice("local", num_cpus=2)
NOT_COMPARED = ("generation", "command", "code_version")  # how and when it was run, not content


def _manifest(root: Path) -> dict:
    manifest = json.loads((root / MANIFEST).read_text())
    return {k: v for k, v in manifest.items() if k not in NOT_COMPARED}


def assert_same_dataset(made: Path, reference: Path) -> None:
    """Same manifest (but for how it was run) and the same run files, byte for byte, and no
    other run file in the folder."""
    assert _manifest(made) == _manifest(reference)
    listed = json.loads((reference / MANIFEST).read_text())["splits"]
    for split in SPLITS:
        indices = [entry["run_index"] for entry in listed[split]["runs"]]
        for k in indices:
            made_bytes = run_path(made, split, k).read_bytes()
            assert made_bytes == run_path(reference, split, k).read_bytes(), f"{split} run {k}"
        assert sorted(p.name for p in (made / "runs" / split).iterdir()) == [
            run_path(made, split, k).name for k in sorted(indices)
        ]


def test_a_dataset_made_on_ray_is_the_local_pools_byte_for_byte(
    smoke_dataset: Path, smoke_spec: DatasetSpec, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "ray"
    dataset = generate(out, smoke_spec, progress=True, command="pytest", cluster=LOCAL_RAY)
    assert_same_dataset(out, smoke_dataset)
    pool = dataset.manifest["generation"]["pool"]
    assert pool == {"kind": "ray", "nodes": 1, "cpus": 2}
    err = capfd.readouterr().err
    assert "ray cluster" in err and "1 node(s), 2 CPU(s), up to 4 runs in flight" in err
    assert "train: 100%" in err  # the same progress lines as the local pool's


def test_a_worker_killed_mid_run_costs_only_that_run(
    smoke_dataset: Path,
    smoke_spec: DatasetSpec,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from sim_harness.sim.ray_pool import KILL_ONCE_ENV

    marks = tmp_path / "killed"
    marks.mkdir()
    victim = f"train-run-{smoke_spec.run_index('train', 1)}"
    monkeypatch.setenv(KILL_ONCE_ENV, f"{victim}@{marks}")  # Ray's workers inherit it
    out = tmp_path / "ray"
    # Workers write their runs themselves into the shared folder (here: the same one).
    generate(
        out,
        smoke_spec,
        progress=False,
        cluster=ClusterChoice("local", shared_dir=out, num_cpus=2),
    )
    assert [p.name for p in marks.iterdir()] == [victim]  # its first attempt was killed
    assert_same_dataset(out, smoke_dataset)


def test_experiments_on_ray_give_the_local_pools_results(untrained_policy_path: Path) -> None:
    config = SuiteConfig(
        suite="paper",
        model_path=untrained_policy_path,
        n_seeds=2,
        seed_base=1010,
        duration_s=1.0,
        experiments=("common",),
    )
    local = run_suite(config)
    seen: list[tuple[int, int]] = []
    on_ray = run_suite(config, on_run=lambda r, done, n: seen.append((done, n)), cluster=LOCAL_RAY)
    assert seen == [(k, 4) for k in range(1, 5)]
    assert experiment_table(on_ray, "common") == experiment_table(local, "common")
    assert on_ray.model_sha256 == local.model_sha256
    for a, b in zip(on_ray.runs, local.runs, strict=True):
        assert (a.controller, a.seed) == (b.controller, b.seed)
        assert a.summary == b.summary
        np.testing.assert_array_equal(a.log.pos_world_enu, b.log.pos_world_enu)


def test_an_aggregation_round_on_ray_is_the_local_pools_byte_for_byte(
    untrained_policy_path: Path, tmp_path: Path
) -> None:
    rules = DatasetSpec(collision_m=0.5, max_run_s=0.8)
    config = AggregateConfig(model_path=untrained_policy_path, runs=10, rules=rules)
    aggregate(tmp_path / "local", config, progress=False)
    aggregate(tmp_path / "ray", config, progress=False, cluster=LOCAL_RAY)
    assert_same_dataset(tmp_path / "ray", tmp_path / "local")
