"""The bar's criteria: each passes exactly when its target holds, and says which seeds fail it."""

import pytest

from sim_harness.experiments.bar import bar_checks, r2_check
from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.experiments.suites import SuiteConfig
from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.rollout import fly, summarize
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

SEEDS = (1000, 1001, 1002, 1003)


@pytest.fixture(scope="module")
def tiny_log():
    scenario = build_scenario(
        ScenarioConfig(name="opposing", n_agents=3, seed=1000, duration_s=0.2)
    )
    return fly(scenario, TeacherController(scenario.config.flocking))


def run(log, experiment, controller, seed, **summary):
    base = {
        "collision_free": True,
        "d_min_m": 1.4,
        "d_max_m": 6.0,
        "arrived": True,
        "arrival_time_s": 30.0,
        "flock_split": False,
        "order_mean": 0.95,
        "centroid_progress_m": 6.0,
        "r_max_m": 20.0,
    }
    return RunRecord(experiment, controller, seed, log, {**summarize(log), **base, **summary})


def suite(log, experiment, cnn, teacher=None, metadata=None):
    """Teacher runs (default: the base values) and CNN runs, one per seed in order."""
    teacher = teacher or [{}] * len(cnn)
    runs = [run(log, experiment, "teacher", s, **t) for s, t in zip(SEEDS, teacher, strict=False)]
    runs += [run(log, experiment, "cnn", s, **c) for s, c in zip(SEEDS, cnn, strict=False)]
    return SuiteResult(SuiteConfig(suite="bar", n_seeds=4), runs, "0" * 64, metadata or {})


def verdicts(result):
    return {c.name.split(": ", 1)[1]: c.passed for c in bar_checks(result)}


def test_common_goal_needs_margin_arrival_and_speed(tiny_log) -> None:
    good = [
        {"d_min_m": d, "arrival_time_s": t}
        for d, t in zip((1.2, 1.1, 1.06, 1.3), (32, 33, 34, 35), strict=True)
    ]
    assert all(verdicts(suite(tiny_log, "common", good)).values())
    close = [*good[:3], {"d_min_m": 1.02}]  # above 1 m, inside the 1.05 m margin
    v = verdicts(suite(tiny_log, "common", close))
    assert v["no pair under 1 m in any run"] and not v["lowest closest pair >= 1.05 m"]
    slow = [{"arrival_time_s": t} for t in (34.0, 35.0, 35.0, 36.0)]  # median 35 s: 1.17x
    v = verdicts(suite(tiny_log, "common", slow))
    assert not v["median arrival <= 1.15x the teacher's"] and v["every run arrives"]
    stalled = [*good[:3], {"arrived": False, "arrival_time_s": None}]
    checks = bar_checks(suite(tiny_log, "common", stalled))
    arrive = next(c for c in checks if c.name.endswith("every run arrives"))
    assert not arrive.passed and "seeds [1003]" in arrive.detail
    bumped = [*good[:3], {"collision_free": False, "d_min_m": 0.97}]
    checks = bar_checks(suite(tiny_log, "common", bumped))
    assert not checks[0].passed and "1003 (0.97 m)" in checks[0].detail


def test_opposing_goals_need_drift_order_and_the_teachers_margin(tiny_log) -> None:
    teacher = [{"d_min_m": d, "centroid_progress_m": 6.5} for d in (0.8, 0.9, 1.0, 0.7)]
    good = [
        {"d_min_m": d, "centroid_progress_m": 3.5, "order_mean": 0.6}
        for d in (0.75, 0.85, 1.1, 0.65)
    ]
    assert all(verdicts(suite(tiny_log, "opposing", good, teacher)).values())
    tug = [{**g, "centroid_progress_m": 0.5, "order_mean": 0.03} for g in good]
    v = verdicts(suite(tiny_log, "opposing", tug, teacher))
    assert not v["mean order parameter >= 0.5"]
    assert not next(ok for name, ok in v.items() if name.startswith("the centroid drifts"))
    closer = [*good[:3], {**good[3], "d_min_m": 0.55}]  # 0.15 m below the teacher's 0.7 m
    checks = bar_checks(suite(tiny_log, "opposing", closer, teacher))
    margin = next(c for c in checks if "below the teacher's" in c.name)
    assert not margin.passed and "1003 (0.55 vs 0.70 m)" in margin.detail
    split = [*good[:3], {**good[3], "flock_split": True, "d_max_m": 25.0}]
    assert not verdicts(suite(tiny_log, "opposing", split, teacher))[
        "the flock never splits (d_max < r_max)"
    ]


def test_small_and_large_flocks_need_order_and_the_looser_arrival(tiny_log) -> None:
    ok = [{"arrival_time_s": t, "order_mean": 0.92} for t in (36.0, 38.0, 38.0, 40.0)]  # 1.27x
    assert all(verdicts(suite(tiny_log, "n3", ok)).values())
    loose = [{**o, "order_mean": 0.8} for o in ok]
    assert not verdicts(suite(tiny_log, "n12", loose))["mean order parameter >= 0.9"]
    crawl = [{"arrival_time_s": 60.0}] * 2 + [{"arrived": False, "arrival_time_s": None}] * 2
    checks = bar_checks(suite(tiny_log, "n3", crawl))
    ratio = next(c for c in checks if "median arrival" in c.name)
    assert not ratio.passed and "never (half or more stalled)" in ratio.detail


def test_a_collision_verdict_is_the_cnns_and_shows_the_teachers_on_the_same_seeds(
    tiny_log,
) -> None:
    crowded = [{}] * 2 + [{"collision_free": False, "d_min_m": 0.86}] * 2  # the teacher's
    clear = [{"d_min_m": 1.02}] * 4
    check = bar_checks(suite(tiny_log, "n12", clear, crowded))[0]
    assert check.passed
    assert "4/4 runs clear; lowest pair 1.02 m (teacher, same seeds: 2/4 clear, lowest 0.86 m)" in (
        check.detail
    )
    bumped = [*clear[:3], {"collision_free": False, "d_min_m": 0.95}]
    check = bar_checks(suite(tiny_log, "n12", bumped))[0]  # the teacher's runs all clear
    assert not check.passed and "1003 (0.95 m) (teacher, same seeds: 4/4 clear" in check.detail


def test_a_distance_on_the_wrong_side_of_a_bound_never_reads_as_the_bound(tiny_log) -> None:
    """0.998 m fails "no pair under 1 m": rounded to cm it would read 1.00 m, so it reads in mm."""
    hair = [{}] * 3 + [{"collision_free": False, "d_min_m": 0.998}]
    check = bar_checks(suite(tiny_log, "vmax4", hair))[0]
    assert not check.passed
    assert "lowest pair 0.998 m; under 1 m: 1003 (0.998 m)" in check.detail
    common = [{"d_min_m": 1.0496}] + [{}] * 3
    lowest = bar_checks(suite(tiny_log, "common", common))[1]
    assert not lowest.passed and "lowest 1.050 m;" in lowest.detail
    teacher = [{"d_min_m": 1.5}] * 4
    inside = [{"d_min_m": 1.5}] * 3 + [{"d_min_m": 1.5 - 0.1004}]  # 0.1004 m below: fails
    margin = next(
        c
        for c in bar_checks(suite(tiny_log, "opposing", inside, teacher))
        if "below the teacher's" in c.name
    )
    assert not margin.passed and "worst -0.100 m" in margin.detail
    clear = [{"d_min_m": 1.234}] * 4  # away from every bound: cm, as before
    assert "lowest pair 1.23 m" in bar_checks(suite(tiny_log, "vmax4", clear))[0].detail


def test_faster_flock_and_no_goal_have_their_own_criteria(tiny_log) -> None:
    assert list(verdicts(suite(tiny_log, "vmax4", [{}] * 4))) == [
        "no pair under 1 m in any run",
        "median arrival <= 1.3x the teacher's",
    ]
    drifted = [{}] * 3 + [{"flock_split": True}]
    assert verdicts(suite(tiny_log, "self-propelled", drifted)) == {
        "no pair under 1 m in any run": True,
        "the flock never splits (d_max < r_max)": False,
    }


def test_the_r2_aim_reads_the_models_test_metrics(tiny_log) -> None:
    per_axis = {"x": {"r2": 0.86}, "y": {"r2": 0.9}, "z": {"r2": 0.84}}
    check = r2_check({"test_metrics": {"metrics": {"per_axis": per_axis}}})
    assert check is not None and not check.passed and "z 0.840" in check.detail
    assert r2_check({}) is None
    metadata = {"test_metrics": {"metrics": {"per_axis": {a: {"r2": 0.9} for a in "xyz"}}}}
    checks = bar_checks(suite(tiny_log, "common", [{}] * 4, metadata=metadata))
    assert checks[-1].name.startswith("aim: R²") and checks[-1].passed
    assert bar_checks(SuiteResult(SuiteConfig(suite="bar"), [], "0" * 64, metadata)) == []
