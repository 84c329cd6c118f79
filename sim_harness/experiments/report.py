"""One Markdown report per suite, with its PNGs and a JSON of every number in it.

`write_report(result, out_dir)` writes into `out_dir`:

- `report.md`: the model and seeds, the bar (when the suite flew common and opposing goals), the
  figures, one aggregate table per experiment (a row per controller), one table per experiment and
  controller (a row per seed), the Grad-CAM strip and the timings;
- `paper_figure.png`: the paper's layout (rows: teacher top view, CNN top view, distances, order;
  columns: common and opposing goals), when both were flown;
- `experiments_figure.png`: the same rows for the other experiments of the suite;
- `gradcam.png`: one agent's view early in a CNN flight, with the Grad-CAM of its command;
- `results.json`: the suite's configuration, model, tables, bar, timings and every run's summary.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sim_harness.experiments import stats as suite_stats
from sim_harness.experiments.bar import BarCheck, bar_checks
from sim_harness.experiments.gradcam_strip import save_gradcam_strip
from sim_harness.experiments.machine import machine
from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.experiments.suites import (
    CONTROLLERS,
    DEFAULT_SEEDS,
    EXPERIMENTS,
    LABELS,
    SuiteConfig,
)
from sim_harness.sim.plots import BANDS_KEY, TRAJECTORY_KEY, save_comparison_figure
from sim_harness.sim.rollout import FlightLog

log = logging.getLogger(__name__)

GRADCAM_TIME_S = 1.0  # "early in the flight"


def _num(x: float | None, digits: int = 2, unit: str = "") -> str:
    return "—" if x is None else f"{x:.{digits}f}{unit}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines + [""]


def _aggregate_table(table: dict[str, dict[str, Any]]) -> list[str]:
    header = [
        "controller",
        "runs",
        "no collision (< 1 m)",
        "physical contacts",
        "lowest d_min",
        "median d_min",
        "highest d_max",
        "mean order",
        "centroid progress",
        "arrived",
        "median arrival",
        "CNN / teacher",
        "split",
        "stalled",
    ]
    rows = []
    for controller, row in table.items():
        n = row["runs"]
        ratio = row["arrival_ratio_to_teacher"] if controller != "teacher" else None
        rows.append(
            [
                LABELS.get(controller, controller),
                str(n),
                f"{row['collision_free_runs']}/{n}",
                f"{row['contact_runs']}/{n}",
                _num(row["d_min_lowest_m"], unit=" m"),
                _num(row.get("d_min_median_m"), unit=" m"),
                _num(row["d_max_highest_m"], unit=" m"),
                _num(row["order_mean"]),
                _num(row.get("centroid_progress_median_m"), 1, " m"),
                f"{row['arrived_runs']}/{n}",
                _num(row["arrival_median_s"], 1, " s"),
                _num(ratio) + ("x" if ratio is not None else ""),
                f"{row['split_runs']}/{n}",
                "n/a" if row["stalled_runs"] is None else f"{row['stalled_runs']}/{n}",
            ]
        )
    return _table(header, rows)


def _runs_table(records: list[RunRecord]) -> list[str]:
    header = [
        "seed",
        "end",
        "arrival",
        "d_min",
        "d_max",
        "mean order",
        "centroid progress",
        "contacts",
        "split",
    ]
    rows = [
        [
            str(r.seed),
            r.summary["stop_reason"],
            _num(r.summary["arrival_time_s"], 1, " s"),
            _num(r.summary["d_min_m"], unit=" m"),
            _num(r.summary["d_max_m"], unit=" m"),
            _num(r.summary["order_mean"]),
            _num(r.summary.get("centroid_progress_m"), 1, " m"),
            str(r.summary["physical_contacts"]),
            "yes" if r.summary["flock_split"] else "no",
        ]
        for r in records
    ]
    return _table(header, rows)


def _figure_columns(
    result: SuiteResult, keys: Sequence[str]
) -> dict[str, dict[str, list[FlightLog]]]:
    return {EXPERIMENTS[k].title: {LABELS[c]: result.logs(k, c) for c in CONTROLLERS} for k in keys}


def _figures(result: SuiteResult, out_dir: Path) -> list[tuple[Path, str, str]]:
    flown = [e.key for e in result.config.experiment_list]
    paper = [k for k in ("common", "opposing") if k in flown]
    figures: list[tuple[Path, str, str]] = []
    key = f"{TRAJECTORY_KEY}. Below them, the {BANDS_KEY}"
    if len(paper) == 2:
        path = save_comparison_figure(_figure_columns(result, paper), out_dir / "paper_figure.png")
        title = "The paper's figure: teacher and CNN, common and opposing goals"
        figures.append((path, title, key))
    others = [k for k in flown if len(paper) < 2 or k not in paper]
    if others:
        path = save_comparison_figure(
            _figure_columns(result, others), out_dir / "experiments_figure.png", dpi=70
        )
        figures.append((path, "Teacher and CNN, one column per experiment", key))
    return figures


def _find_per_axis(metrics: Any) -> dict[str, Any] | None:
    """The first `{"per_axis": ..., "overall": ...}` block in the test metrics, if any."""
    if isinstance(metrics, dict):
        if isinstance(metrics.get("per_axis"), dict):
            return metrics
        for value in metrics.values():
            found = _find_per_axis(value)
            if found is not None:
                return found
    return None


def _model_lines(result: SuiteResult) -> list[str]:
    meta = result.model_metadata
    lines = [f"- Model: `{result.config.model_path}` (SHA-256 `{result.model_sha256}`)"]
    dataset = meta.get("dataset")
    if isinstance(dataset, dict) and dataset.get("id"):
        counts = dataset.get("counts")
        samples = f" ({_counts_text(counts)} samples)" if isinstance(counts, dict) else ""
        lines.append(f"- Trained on dataset `{dataset['id']}`{samples}")
    block = _find_per_axis(meta.get("test_metrics"))
    if block is not None:
        r2 = {k: v.get("r2") for k, v in block["per_axis"].items() if isinstance(v, dict)}
        overall = block.get("overall", {}).get("r2")
        parts = ", ".join(f"{k} {_num(v)}" for k, v in r2.items())
        lines.append(f"- Test split R²: {parts}; overall {_num(overall)}")
    lines += _export_lines(meta)
    training = meta.get("training")
    if isinstance(training, dict):
        lines += _training_lines(training)
    return lines


def _export_lines(meta: dict[str, Any]) -> list[str]:
    """How the export shaped the policy: the views it averages over and its output gain."""
    parts = []
    members = meta.get("ensemble")
    runtime = meta.get("runtime")
    symmetry = runtime.get("symmetry") if isinstance(runtime, dict) else None
    if isinstance(members, list):
        described = ", ".join(
            f"{m.get('weight'):g} x `{m.get('model')}` ({m.get('arch')}, `{m.get('symmetry')}`)"
            for m in members
            if isinstance(m, dict)
        )
        views = f"; {symmetry.get('views')} network calls an image" if symmetry else ""
        parts.append(f"an ensemble, the answers of {described} averaged{views}")
    elif isinstance(symmetry, dict) and symmetry.get("group") not in (None, "none"):
        parts.append(f"averaged over {symmetry.get('views')} views (`{symmetry['group']}`)")
    training = meta.get("training")
    gain = training.get("output_gain") if isinstance(training, dict) else None
    if isinstance(gain, (int, float)) and gain != 1.0:
        parts.append(f"every answer multiplied by the output gain {gain:g}")
    return [f"- Exported policy: {'; '.join(parts)}"] if parts else []


def _counts_text(counts: dict[str, Any]) -> str:
    """Samples per split as `train 423,693 / val 8,622 / test 8,037`."""
    order = [s for s in ("train", "val", "test") if s in counts]
    order += sorted(s for s in counts if s not in order)
    return " / ".join(
        f"{s} {counts[s]:,}" if isinstance(counts[s], int) else f"{s} {counts[s]}" for s in order
    )


def _training_lines(training: dict[str, Any]) -> list[str]:
    """Every training command that led to the model, first to last, when its metadata has them.

    `training.chain` (recorded by `swarm-sim export`) lists them; an older export records only its
    last command, which the report then says. A model averaged or ensembled from networks with a
    common ancestor records that ancestor's commands once per network: each is listed once, where
    it first appears.
    """
    chain = training.get("chain")
    if isinstance(chain, list) and chain:
        unique = list(dict.fromkeys(str(command) for command in chain))
        lines = ["- Training commands, first to last:"]
        lines += [f"  {k}. `{command}`" for k, command in enumerate(unique, start=1)]
        if len(unique) < len(chain):
            shared = len(chain) - len(unique)
            lines.append(
                f"  ({shared} more recorded by the histories this model merges, each the same"
                " command as one above, are listed once)"
            )
        if not training.get("chain_complete", True):
            lines.append("  (the steps before the first one are not recorded)")
        return lines
    command = training.get("command")
    if not command:
        return []
    config = training.get("config")
    init_from = config.get("init_from") if isinstance(config, dict) else None
    what = f"a fine-tune of `{init_from}`; " if init_from else ""
    return [
        f"- Training command ({what}the model's metadata records only this last step): `{command}`"
    ]


def _timing_lines(result: SuiteResult) -> list[str]:
    header = [
        "experiment",
        "controller",
        "N",
        "flights",
        "render ms/step",
        "inference ms/step",
        "physics ms/step",
        "real-time factor",
    ]
    rows = []
    timings: dict[str, dict[str, Any]] = {}
    for e in result.config.experiment_list:
        for c in CONTROLLERS:
            t = suite_stats.timing_row(result.records(e.key, c))
            timings[f"{e.key}/{c}"] = t
            rows.append(
                [
                    e.key,
                    LABELS[c],
                    str(e.n_agents),
                    str(t["flights"]),
                    _num(t["render_ms_per_step"], 1),
                    _num(t["inference_ms_per_step"], 1),
                    _num(t["physics_ms_per_step"], 1),
                    _num(t["real_time_factor"]) + "x",
                ]
            )
    return _table(header, rows)


def bar_scope(config: SuiteConfig, demo: bool = False) -> str:
    """What the bar was checked on: `10 seeds`, or e.g. `demo checks, 1 seed` below the bar's."""
    n = len(config.seeds)
    seeds = f"{n} seed" + ("" if n == 1 else "s")
    if n >= DEFAULT_SEEDS["bar"]:
        return seeds
    return f"{'demo' if demo else config.suite + ' suite'} checks, {seeds}"


def write_report(
    result: SuiteResult, out_dir: Path, gradcam: bool = True, demo: bool = False
) -> Path:
    """Write `report.md`, its figures and `results.json` into `out_dir`; returns the report.

    `demo`: the suite is `swarm-sim demo`'s (its bar heading says so)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = result.config
    seeds = cfg.seeds
    cutoff = cfg.low_pass_cutoff_hz
    lines = [
        f"# Suite `{cfg.suite}`: teacher and CNN, same seeds",
        "",
        *_model_lines(result),
        f"- Seeds: {seeds[0]}..{seeds[-1]} ({len(seeds)} per experiment and controller; "
        "evaluation seeds >= 1000, never used for training)",
        f"- CNN low-pass filter: {'off' if cutoff is None else f'{cutoff:g} Hz cut-off'}; "
        f"physics {cfg.rates.physics_hz} Hz, control {cfg.rates.control_hz} Hz; "
        f"CNN images drawn by the `{cfg.renderer}` renderer"
        + ("" if cfg.duration_s is None else f"; every flight cut at {cfg.duration_s:g} s")
        + (
            f"; **sensitivity check: seeded noise of up to {cfg.output_jitter_mps:g} m/s added "
            "to every CNN output component**"
            if cfg.output_jitter_mps
            else ""
        )
        + (
            f"; **robustness check: the CNN's images drawn over unseen ground number "
            f"{cfg.ground_seed}** (`--ground`)"
            if cfg.ground_seed is not None
            else ""
        ),
        f"- {len(result.runs)} flights in {result.wall_time_s:.0f} s of wall time",
        "",
        "Collision: a pair under 1 m at any control step. Split: d_max >= r_max at some step. "
        "Stalled: no arrival by the time limit (only for experiments with a common goal). "
        "Arrival ratio: median CNN arrival time over the teacher's, same seeds. Centroid "
        "progress: how far the whole flock's centroid moved towards the goal that ends the run "
        "(the majority's, with opposing goals); median over runs in the tables.",
        "",
    ]
    checks = bar_checks(result)
    if checks:
        passed = all(c.passed for c in checks)
        verdict = "met" if passed else "NOT met"
        lines += [f"## The bar ({bar_scope(cfg, demo)}): {verdict}", ""]
        if len(seeds) < DEFAULT_SEEDS["bar"]:
            lines += [
                f"Checked on these {len(seeds)}-seed flights only. The bar itself is judged on "
                f"{DEFAULT_SEEDS['bar']} evaluation seeds (`swarm-sim experiments --suite bar "
                "--workers 2`; the README gives the shipped model's result), where a verdict can "
                "differ.",
                "",
            ]
        lines += _table(
            ["criterion", "result", "measured"],
            [[c.name, "pass" if c.passed else "FAIL", c.detail] for c in checks],
        )
    lines += ["## Figures", ""]
    for path, title, key in _figures(result, out_dir):
        lines += [f"![{title}]({path.name})", "", f"*{title}. {key}.*", ""]
    tables: dict[str, Any] = {}
    for e in cfg.experiment_list:
        table = suite_stats.experiment_table(result, e.key)
        tables[e.key] = table
        lines += [f"## {e.title}", "", *_aggregate_table(table)]
        for c in CONTROLLERS:
            lines += [f"### {e.title}: {LABELS[c]}, per run", ""]
            lines += _runs_table(result.records(e.key, c))
    if gradcam:
        strip = save_gradcam_strip(result, out_dir / "gradcam.png", GRADCAM_TIME_S)
        if strip is not None:
            lines += ["## Grad-CAM", "", f"![Grad-CAM]({strip.path.name})", "", strip.caption, ""]
    where = machine()
    lines += [
        "## Timings (wall clock, this machine)",
        "",
        f"{where['cpu']}, {where['cpus']} CPUs, torch {where['torch']}: the CNN's flights "
        "repeat exactly on one machine, not across machines (a flock amplifies float rounding).",
        "",
        *_timing_lines(result),
    ]
    report = out_dir / "report.md"
    report.write_text("\n".join(lines).rstrip() + "\n")
    _write_json(result, out_dir / "results.json", tables, checks, where)
    return report


def _write_json(
    result: SuiteResult,
    path: Path,
    tables: dict[str, Any],
    checks: list[BarCheck],
    where: dict[str, Any],
) -> None:
    cfg = result.config
    data = {
        "suite": cfg.suite,
        "model": {"path": str(cfg.model_path), "sha256": result.model_sha256},
        "seeds": list(cfg.seeds),
        "low_pass_cutoff_hz": cfg.low_pass_cutoff_hz,
        "renderer": cfg.renderer,
        "duration_s": cfg.duration_s,
        "output_jitter_mps": cfg.output_jitter_mps,
        "ground_seed": cfg.ground_seed,
        "rates": {"physics_hz": cfg.rates.physics_hz, "control_hz": cfg.rates.control_hz},
        "wall_time_s": result.wall_time_s,
        "machine": where,
        "tables": tables,
        "bar": [{"name": c.name, "passed": c.passed, "detail": c.detail} for c in checks],
        "timings": {
            f"{e.key}/{c}": suite_stats.timing_row(result.records(e.key, c))
            for e in cfg.experiment_list
            for c in CONTROLLERS
        },
        "runs": [
            {**r.summary, "experiment": r.experiment, "stage_time_s": r.log.stage_time_s}
            for r in result.runs
        ],
    }
    path.write_text(json.dumps(data, indent=2) + "\n")
