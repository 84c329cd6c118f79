"""Evaluation: metrics computed right, tables that add up, files written, the CLI."""

import json
import math

import numpy as np
import pytest
import torch

from sim_harness.cli import main
from sim_harness.dataset.store import open_dataset
from sim_harness.learning.evaluate import (
    errors_by_bin,
    errors_by_value,
    evaluate_split,
    predict,
    regression_metrics,
)
from sim_harness.learning.export import export_policy
from sim_harness.learning.model import build_model


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    net = build_model(pixel_mean=185.0, pixel_std=36.0)
    with torch.no_grad():
        net.head.weight.normal_(0.0, 0.002)
    return net.eval()


def test_metrics_match_hand_computed_values() -> None:
    target = np.array([[1.0, 0.0, 2.0], [3.0, 0.0, 2.0], [5.0, 0.0, 2.0]])
    pred = np.array([[2.0, 1.0, 2.0], [3.0, -1.0, 2.0], [4.0, 0.0, 2.0]])
    m = regression_metrics(pred, target)
    assert m["n_samples"] == 3
    x = m["per_axis"]["x"]
    assert x["mse"] == pytest.approx(2.0 / 3.0)
    assert x["rmse"] == pytest.approx(math.sqrt(2.0 / 3.0))
    assert x["r2"] == pytest.approx(1.0 - 2.0 / 8.0)  # SS_tot = 4 + 0 + 4
    assert m["per_axis"]["y"]["r2"] is None  # constant target: undefined, not -inf
    assert m["per_axis"]["z"] == {"mse": 0.0, "rmse": 0.0, "r2": None}
    assert m["overall"]["mse"] == pytest.approx(4.0 / 9.0)
    assert m["overall"]["r2"] == pytest.approx(1.0 - 4.0 / 8.0)  # pooled over the axes


def test_predicting_the_mean_scores_r2_zero_and_perfect_scores_one() -> None:
    rng = np.random.default_rng(0)
    target = rng.normal(size=(200, 3))
    mean = np.broadcast_to(target.mean(axis=0), target.shape)
    assert regression_metrics(mean, target)["overall"]["r2"] == pytest.approx(0.0, abs=1e-12)
    perfect = regression_metrics(target, target)
    assert all(perfect["per_axis"][a]["r2"] == 1.0 for a in "xyz")
    with pytest.raises(ValueError):
        regression_metrics(target[:, :2], target[:, :2])


def test_error_tables_group_and_count() -> None:
    err_sq = np.array([3.0, 12.0, 27.0, 0.0])  # |e|^2 of errors (1,1,1), (2,2,2), (3,3,3), 0
    by_n = errors_by_value(err_sq, np.array([2, 2, 5, 8]))
    assert [(r["value"], r["count"]) for r in by_n] == [(2, 2), (5, 1), (8, 1)]
    assert by_n[0]["rmse_mps"] == pytest.approx(math.sqrt((3.0 + 12.0) / 2 / 3))
    assert by_n[0]["mean_error_mps"] == pytest.approx((math.sqrt(3.0) + math.sqrt(12.0)) / 2)
    by_d = errors_by_bin(err_sq, np.array([1.2, 1.4, 9.0, np.nan]), [0.0, 1.5, 7.0, math.inf])
    assert [(r["label"], r["count"]) for r in by_d] == [("0-1.5", 2), (">=7", 1), ("none", 1)]


def test_evaluate_split_reports_and_writes(model, smoke_dataset, tmp_path) -> None:
    split = open_dataset(smoke_dataset).split("test")
    report = evaluate_split(model, split, tmp_path)
    saved = np.load(tmp_path / "predictions.npz")
    with torch.inference_mode():
        direct = model(torch.from_numpy(np.array(split.images[:4])))
    np.testing.assert_allclose(saved["pred"][:4], direct.numpy(), atol=1e-6)
    np.testing.assert_array_equal(saved["target"], split.targets)
    assert report["metrics"] == regression_metrics(saved["pred"], saved["target"])
    assert json.loads((tmp_path / "metrics.json").read_text()) == report
    assert sum(r["count"] for r in report["by_n_neighbours"]) == split.n_samples
    assert sum(r["count"] for r in report["by_nearest_m"]) == split.n_samples
    for name in ("pred_vs_target.png", "error_breakdown.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name


def test_predict_batches_do_not_change_the_answer(model, smoke_dataset) -> None:
    images = open_dataset(smoke_dataset).split("val").images[:50]
    np.testing.assert_allclose(predict(model, images, 7), predict(model, images, 64), atol=1e-5)


def test_swarm_sim_evaluate_a_policy_file(model, smoke_dataset, tmp_path, capsys) -> None:
    policy = tmp_path / "policy.pt"
    export_policy(model, policy, {"id": "smoke"}, None, {"command": "test"})
    out = tmp_path / "eval"
    args = ["evaluate", "--model", str(policy), "--dataset", str(smoke_dataset)]
    assert main([*args, "--split", "val", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "n = 180" in printed and "R²" in printed
    report = json.loads((out / "metrics.json").read_text())
    assert report["metrics"]["n_samples"] == 180
