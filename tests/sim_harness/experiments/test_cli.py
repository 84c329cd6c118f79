"""`swarm-sim demo | experiments | dataset aggregate` find the shipped model from any folder."""

import argparse
import json

from sim_harness.cli import main
from sim_harness.experiments.cli import add_aggregate_command, add_experiment_commands
from sim_harness.learning.shipped import SHIPPED_MODEL_PATH


def test_the_shipped_model_is_found_from_another_working_folder(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    add_experiment_commands(sub)
    add_aggregate_command(sub.add_parser("dataset").add_subparsers())
    for args in (["demo"], ["experiments"]):
        model = parser.parse_args(args).model
        assert model == SHIPPED_MODEL_PATH and model.is_absolute() and model.is_file()


def test_a_missing_model_names_the_path_it_looked_at(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    for args in (["demo"], ["dataset", "aggregate", "--out", "agg"]):
        assert main([*args, "--model", "missing.pt"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"swarm-sim: error: no model at missing.pt (that is, {tmp_path}/")
        assert f"writes {SHIPPED_MODEL_PATH}" in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_experiments_draw_with_the_renderer_the_model_was_trained_on(tmp_path, capsys) -> None:
    import torch

    from sim_harness.learning.export import export_policy
    from sim_harness.learning.model import build_model

    torch.manual_seed(0)
    model = build_model(pixel_mean=120.0, pixel_std=50.0).eval()  # zero head: hovers
    path = tmp_path / "raycast-trained.pt"
    export_policy(model, path, {"id": "t", "renderer": "raycast"}, None, {"command": "pytest"})
    fly = ["experiments", "--suite", "paper", "--experiments", "common", "--seeds", "1"]
    fly += ["--duration", "0.2", "--no-gradcam", "--quiet", "--no-progress", "--model", str(path)]
    for extra, drawn in (([], "raycast"), (["--renderer", "raycast-aa"], "raycast-aa")):
        out = tmp_path / drawn
        assert main([*fly, "--out", str(out), *extra]) == 0
        assert f"{drawn} images" in capsys.readouterr().out
        assert f"drawn by the `{drawn}` renderer" in (out / "report.md").read_text()
        assert json.loads((out / "results.json").read_text())["renderer"] == drawn
