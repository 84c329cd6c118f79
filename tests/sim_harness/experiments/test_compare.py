"""`swarm-sim compare`: two suite reports of the same seeds, seed by seed."""

import json
import math

import pytest

from sim_harness.cli import main
from sim_harness.experiments.compare import ReportError, compare_runs, load_runs

SEEDS = (1000, 1001)


def run(experiment, seed, d_min, order, controller="cnn"):
    return {
        "experiment": experiment,
        "controller": controller,
        "seed": seed,
        "d_min_m": d_min,
        "order_mean": order,
        "collision_threshold_m": 1.0,
    }


def test_differences_are_b_minus_a_per_seed_with_the_runs_under_the_threshold() -> None:
    a = [run("vmax4", 1000, 1.20, 0.90), run("vmax4", 1001, 0.95, 0.80), run("vmax4", 1002, 1.1, 1)]
    b = [run("vmax4", 1000, 1.10, 0.92), run("vmax4", 1001, 1.05, 0.84), run("vmax4", 1002, 0.9, 1)]
    (c,) = compare_runs(a, b)
    assert [p.seed for p in c.seeds] == [1000, 1001, 1002]
    assert [round(p.delta_m, 6) for p in c.seeds] == [-0.1, 0.1, -0.2]
    assert c.median_abs_delta_m == pytest.approx(0.1)
    assert c.largest_delta.seed == 1002
    assert c.under_threshold_a == [1001] and c.under_threshold_b == [1002]
    mean, se = c.order_a
    assert mean == pytest.approx(0.9)
    assert se == pytest.approx(0.1 / math.sqrt(3))


def test_only_seeds_both_flew_count_and_experiments_come_in_the_suites_order() -> None:
    a = [
        run("opposing", 1000, 1.0, 0.5),
        run("common", 1000, 1.3, 0.9),
        run("common", 1001, 1.2, 1),
    ]
    b = [run("common", 1001, 1.25, 0.9), run("opposing", 1000, 1.1, 0.5), run("n3", 1000, 2, 1)]
    comparisons = compare_runs(a, b)
    assert [c.experiment for c in comparisons] == ["common", "opposing"]
    assert [p.seed for p in comparisons[0].seeds] == [1001]
    assert math.isnan(comparisons[0].order_a[1])  # one run: no standard error


def test_the_controller_picks_whose_flights_are_compared() -> None:
    a = [run("common", 1000, 1.3, 0.9, "teacher"), run("common", 1000, 1.2, 0.9)]
    b = [run("common", 1000, 1.3, 0.9, "teacher"), run("common", 1000, 1.0, 0.9)]
    assert compare_runs(a, b, "teacher")[0].median_abs_delta_m == 0.0
    assert compare_runs(a, b, "cnn")[0].median_abs_delta_m == pytest.approx(0.2)
    with pytest.raises(ReportError, match="controller must be one of teacher, cnn"):
        compare_runs(a, b, "pilot")


def test_reports_of_different_seeds_are_an_error_not_an_empty_table() -> None:
    with pytest.raises(ReportError, match="share no .experiment, seed. flown by the CNN"):
        compare_runs([run("common", 1000, 1.3, 0.9)], [run("common", 2000, 1.3, 0.9)])


def test_an_unreadable_report_names_the_file_and_what_is_wrong(tmp_path) -> None:
    with pytest.raises(ReportError, match="no such file"):
        load_runs(tmp_path / "missing")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ReportError, match="bad.json: not a readable results.json"):
        load_runs(bad)
    bad.write_text(json.dumps({"suite": "bar"}))
    with pytest.raises(ReportError, match="has no 'runs' list"):
        load_runs(bad)
    bad.write_text(json.dumps({"runs": [{"experiment": "common", "seed": 1}]}))
    with pytest.raises(ReportError, match=r"runs\[0\] lacks one of"):
        load_runs(bad)
    bad.write_text(json.dumps({"runs": [{**run("common", 1000, 1.0, 0.9), "d_min_m": None}]}))
    with pytest.raises(ReportError, match=r"runs\[0\].d_min_m is None, not a distance"):
        load_runs(bad)
    assert main(["compare", str(tmp_path / "missing"), str(bad)]) == 2


@pytest.fixture(scope="module")
def two_reports(untrained_policy_path, tmp_path_factory):
    """The paper suite flown twice on the same seeds, the second with the CNN's outputs nudged."""
    out = []
    for jitter in ("0", "0.05"):
        folder = tmp_path_factory.mktemp(f"jitter-{jitter}")
        args = ["experiments", "--suite", "paper", "--seeds", str(len(SEEDS)), "--duration", "0.4"]
        args += ["--model", str(untrained_policy_path), "--out", str(folder), "--quiet"]
        assert main([*args, "--no-gradcam", "--output-jitter", jitter]) == 0
        out.append(folder)
    return out


def summary(folder, experiment, controller, seed):
    path = folder / "runs" / experiment / controller / f"seed-{seed}" / "summary.json"
    return json.loads(path.read_text())


def test_compare_reads_two_real_reports_and_lists_each_seeds_pairs(two_reports, tmp_path, capsys):
    a, b = two_reports
    figures = tmp_path / "cmp.json"
    assert main(["compare", str(a), str(b / "results.json"), "--json", str(figures)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"# {a} (A) against {b / 'results.json'} (B)")
    data = json.loads(figures.read_text())
    assert [c["experiment"] for c in data] == ["common", "opposing"]
    for c in data:
        assert [s["seed"] for s in c["seeds"]] == list(SEEDS)
        for s in c["seeds"]:
            d_a = summary(a, c["experiment"], "cnn", s["seed"])["d_min_m"]
            d_b = summary(b, c["experiment"], "cnn", s["seed"])["d_min_m"]
            assert (s["d_min_a_m"], s["d_min_b_m"]) == (d_a, d_b)
            assert s["delta_m"] == pytest.approx(d_b - d_a)
            assert f"| {s['seed']} | {d_a:.3f} m | {d_b:.3f} m |" in text


def test_the_teachers_flights_repeat_exactly_when_only_the_cnn_was_perturbed(
    two_reports, tmp_path, capsys
) -> None:
    a, b = two_reports
    figures = tmp_path / "teacher.json"
    assert main(["compare", str(a), str(b), "--controller", "teacher", "--json", str(figures)]) == 0
    for c in json.loads(figures.read_text()):
        assert c["median_abs_delta_m"] == 0.0 and c["largest_delta"]["delta_m"] == 0.0
        assert c["order_a"] == c["order_b"]
    assert "| common | teacher | 2 | 0.000 m |" in capsys.readouterr().out
