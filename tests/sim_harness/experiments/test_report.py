"""The suite report: what `swarm-sim experiments` and `swarm-sim demo` write; the bar's logic."""

import json
import math
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import pytest
import torch

from sim_harness.cli import main
from sim_harness.experiments.report import _model_lines
from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.experiments.stats import table_row
from sim_harness.experiments.suites import SuiteConfig
from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.rollout import fly, summarize
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

SEEDS = (1000, 1001)


@pytest.fixture(scope="module")
def paper_suite_dir(untrained_policy_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    args = ["experiments", "--suite", "paper", "--seeds", "2", "--duration", "0.4"]
    code = main([*args, "--model", str(untrained_policy_path), "--out", str(out), "--quiet"])
    assert code == 0
    return out


def summaries(out, experiment, controller):
    folder = out / "runs" / experiment / controller
    return [json.loads((folder / f"seed-{s}" / "summary.json").read_text()) for s in SEEDS]


def test_report_has_the_bar_figures_and_a_table_per_experiment_and_controller(
    paper_suite_dir,
) -> None:
    text = (paper_suite_dir / "report.md").read_text()
    assert text.startswith("# Suite `paper`")
    assert "## The bar (paper suite checks, 2 seeds): NOT met" in text  # 0.4 s: no arrival
    assert "Checked on these 2-seed flights only. The bar itself is judged on 20" in text
    for heading in (
        "## Common goal (N = 9, v_max = 2 m/s)",
        "## Opposing goals (5 vs 4 agents)",
        "### Common goal (N = 9, v_max = 2 m/s): teacher, per run",
        "### Common goal (N = 9, v_max = 2 m/s): CNN, per run",
        "### Opposing goals (5 vs 4 agents): teacher, per run",
        "### Opposing goals (5 vs 4 agents): CNN, per run",
        "## Timings",
    ):
        assert heading in text, heading
    assert "![The paper's figure" in text and "(paper_figure.png)" in text
    caption = text.split("(paper_figure.png)")[1].split("\n\n")[1]
    for mark in ("squares, triangles and circles", "spawn area", "migration points", "dotted"):
        assert mark in caption, mark
    assert "min-max range over runs shaded" in caption
    # Each per-run table lists the seeds with that run's own d_min.
    section = text.split("### Opposing goals (5 vs 4 agents): CNN, per run")[1].split("##")[0]
    for s in summaries(paper_suite_dir, "opposing", "cnn"):
        assert f"| {s['seed']} | time_limit | — | {s['d_min_m']:.2f} m |" in section


def test_paper_figure_has_the_papers_layout(paper_suite_dir) -> None:
    image = mpimg.imread(paper_suite_dir / "paper_figure.png")
    height, width = image.shape[:2]
    # Two columns (common, opposing), four rows (teacher, CNN, distances, order): tall.
    assert 1.1 < height / width < 1.6
    assert image.std() > 0.05  # drawn, not blank


def test_results_json_holds_the_tables_computed_from_the_runs(paper_suite_dir) -> None:
    data = json.loads((paper_suite_dir / "results.json").read_text())
    assert data["suite"] == "paper" and data["seeds"] == list(SEEDS)
    assert len(data["model"]["sha256"]) == 64
    assert data["machine"]["cpu"] and data["machine"]["torch"] == torch.__version__
    assert f"{data['machine']['cpu']}, " in (paper_suite_dir / "report.md").read_text()
    for experiment in ("common", "opposing"):
        for controller in ("teacher", "cnn"):
            runs = summaries(paper_suite_dir, experiment, controller)
            row = data["tables"][experiment][controller]
            assert row["runs"] == 2
            assert row["d_min_lowest_m"] == min(s["d_min_m"] for s in runs)
            assert row["d_max_highest_m"] == max(s["d_max_m"] for s in runs)
            assert row["collision_free_runs"] == sum(s["collision_free"] for s in runs)
            timing = data["timings"][f"{experiment}/{controller}"]
            assert (timing["render_ms_per_step"] > 0) == (controller == "cnn")
    passed = {b["name"]: b["passed"] for b in data["bar"]}
    assert passed["common goal: every run arrives"] is False  # nothing arrived in 0.4 s
    assert len(data["runs"]) == 8


def _record(seed, controller, experiment, log, **changes):
    return RunRecord(experiment, controller, seed, log, {**summarize(log), **changes})


@pytest.fixture(scope="module")
def tiny_log():
    scenario = build_scenario(
        ScenarioConfig(name="opposing", n_agents=3, seed=1000, duration_s=0.2)
    )
    return fly(scenario, TeacherController(scenario.config.flocking))


def arrived(t, **extra):
    return {"arrived": True, "arrival_time_s": t, "collision_free": True, **extra}


def test_table_row_counts_stalls_and_ratio(tiny_log) -> None:
    teacher = [
        _record(s, "teacher", "common", tiny_log, arrived=True, arrival_time_s=30.0)
        for s in (1, 2, 3)
    ]
    cnn = [
        _record(1, "cnn", "common", tiny_log, **arrived(36.0)),
        _record(2, "cnn", "common", tiny_log, **arrived(45.0)),
        _record(3, "cnn", "common", tiny_log, arrived=False, arrival_time_s=None),
    ]
    row = table_row(cnn, teacher, expects_arrival=True)
    assert row["arrived_runs"] == 2 and row["stalled_runs"] == 1
    assert row["arrival_median_s"] == 45.0  # the stalled run counts as never arriving
    assert row["arrival_ratio_to_teacher"] == pytest.approx(1.5)
    assert table_row(cnn, teacher, expects_arrival=False)["stalled_runs"] is None
    worse = [*cnn[:1], *(_record(s, "cnn", "common", tiny_log, arrived=False) for s in (2, 3))]
    assert table_row(worse, teacher, True)["arrival_median_s"] is None
    assert not math.isnan(table_row(teacher, teacher, True)["arrival_ratio_to_teacher"])


def test_demo_without_a_model_says_how_to_get_one(tmp_path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "sim_harness.cli", "demo", "--model", str(tmp_path / "m.pt")],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
    )
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("swarm-sim: error: no model at")
    assert "swarm-sim train" in lines[0] and "--model" in lines[0]
    assert not (tmp_path / "runs").exists()


def test_demo_flies_both_controllers_and_prints_where_the_report_is(
    untrained_policy_path, tmp_path, capsys
) -> None:
    out = tmp_path / "demo"
    args = ["demo", "--model", str(untrained_policy_path), "--out", str(out), "--duration", "0.3"]
    assert main(args) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert f"report: {out / 'report.md'}" in printed
    for name in ("common / teacher / seed 1000", "common / CNN / seed 1000", "opposing / CNN"):
        assert name in printed
        # Each flight shows its progress while it flies: plain lines here (not a terminal).
        progress = [ln for ln in captured.err.splitlines() if ln.startswith(name)]
        assert progress and ": 100% 3/3 [" in progress[-1], name
    assert "\r" not in captured.err
    assert "bar (demo checks, 1 seed): FAIL: common goal: every run arrives" in printed
    assert "## The bar (demo checks, 1 seed): NOT met" in (out / "report.md").read_text()
    data = json.loads((out / "results.json").read_text())
    assert data["seeds"] == [1000]  # the demo's default: one seed
    assert (out / "paper_figure.png").stat().st_size > 0


def test_report_shows_the_gradcam_strip_of_an_early_view(paper_suite_dir) -> None:
    text = (paper_suite_dir / "report.md").read_text()
    assert "## Grad-CAM" in text and "(gradcam.png)" in text
    assert "CNN's common flight, seed 1000" in text
    strip = mpimg.imread(paper_suite_dir / "gradcam.png")
    assert strip.shape[1] >= 1000 and strip.std() > 0.05  # five rows: image + four maps


def test_saliency_explains_what_the_policy_file_predicts(untrained_policy_path, tmp_path) -> None:
    import numpy as np
    import torch

    from companion.model_file import base_metadata, save_model, torchscript_calls
    from sim_harness.experiments.gradcam_strip import saliency
    from sim_harness.experiments.vision_controller import load_policy

    image = np.random.default_rng(5).integers(0, 256, size=(64, 384), dtype=np.uint8)
    heatmaps, vel = saliency(untrained_policy_path, image)
    assert list(heatmaps) == ["|v|", "|v_x|", "|v_y|", "|v_z|"]
    for heat in heatmaps.values():
        assert heat.shape == (64, 384) and heat.min() >= 0.0 and heat.max() <= 1.0
    with load_policy(untrained_policy_path) as policy:
        np.testing.assert_allclose(vel, policy.infer_batch(image[None])[0], atol=1e-4)
    # A policy file without eager weights gets no strip (and no error).
    bare = tmp_path / "bare.pt"
    with torchscript_calls():
        module = torch.jit.load(str(untrained_policy_path))
    save_model(module, base_metadata(), bare)
    assert saliency(bare, image) is None


def _model_text(metadata) -> str:
    config = SuiteConfig(model_path=Path("/models/m.pt"))
    return "\n".join(_model_lines(SuiteResult(config, [], "0" * 64, metadata)))


def test_model_lines_print_counts_as_numbers_per_split_and_the_whole_training_chain() -> None:
    counts = {"test": 8037, "train": 423693, "val": 8622}  # as JSON with sorted keys has them
    chain = ["swarm-sim train --dataset data/quick-s0", "swarm-sim train --init-from m1.pt"]
    text = _model_text(
        {"dataset": {"id": "abc", "counts": counts}, "training": {"chain": chain, "command": "x"}}
    )
    assert "dataset `abc` (train 423,693 / val 8,622 / test 8,037 samples)" in text
    assert "{" not in text
    assert "- Training commands, first to last:" in text
    assert f"  1. `{chain[0]}`" in text and f"  2. `{chain[1]}`" in text


def test_model_lines_list_a_command_shared_by_merged_histories_once() -> None:
    shared = ["swarm-sim train --out runs/train/a", "swarm-sim train --out runs/train/b"]
    chain = [*shared, "swarm-sim average x", *shared, "swarm-sim ensemble y"]
    text = _model_text({"training": {"chain": chain, "command": "swarm-sim ensemble y"}})
    listed = [line for line in text.splitlines() if line.startswith("  ") and "`" in line]
    assert [line.split("`")[1] for line in listed] == [*shared, chain[2], chain[-1]]
    assert "2 more recorded by the histories this model merges" in text


def test_model_lines_say_when_only_the_last_training_command_is_recorded() -> None:
    training = {"command": "swarm-sim train --init-from models/m.pt", "config": {"init_from": "m"}}
    text = _model_text({"training": training})
    assert "only this last step" in text and "a fine-tune of `m`" in text
    assert "`swarm-sim train --init-from models/m.pt`" in text


def test_model_lines_say_how_the_export_shaped_the_policy() -> None:
    d4 = {"runtime": {"symmetry": {"group": "d4", "views": 8}}}
    gained = _model_text({**d4, "training": {"output_gain": 1.3, "command": "x"}})
    assert (
        "- Exported policy: averaged over 8 views (`d4`); every answer multiplied by the "
        "output gain 1.3" in gained
    )
    plain = _model_text(
        {"runtime": {"symmetry": {"group": "none", "views": 1}}, "training": {"output_gain": 1.0}}
    )
    assert "Exported policy" not in plain  # nothing to say for a plain export
    members = [
        {"weight": 0.5, "model": "models/a.pt", "arch": "dronet", "symmetry": "d4"},
        {"weight": 0.5, "model": "models/c.pt", "arch": "cube", "symmetry": "d4"},
    ]
    ensemble = _model_text(
        {"ensemble": members, "runtime": {"symmetry": {"group": "d4+d4", "views": 16}}}
    )
    assert (
        "- Exported policy: an ensemble, the answers of 0.5 x `models/a.pt` (dronet, `d4`), "
        "0.5 x `models/c.pt` (cube, `d4`) averaged; 16 network calls an image" in ensemble
    )
