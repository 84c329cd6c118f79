"""`swarm-sim demo | experiments | dataset aggregate` find the shipped model from any folder."""

import argparse

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
