"""What learning a more cautious law costs on the paper's R², and how well a policy learned it.

    python benchmarks/cautious_law_fit.py --dataset data/quick-aa-s1 [--scales 1.1,1.15,1.2] \
        [--near 2 [--near-m 1.5] [--near-ramp-m 0.3]] [--scale-reach-m 4] \
        [--model models/swarm_cnn.pt --model other.pt ...] [--split test]

`swarm-sim train --separation-scale S` teaches the flocking law with k_sep x S, and
`--near-separation-scale C` that law with the neighbours within 1.2 m (`--near-separation-radius`)
weighing C in its separation sum, ramped in over `--near-separation-ramp` metres
(`sim_harness.learning.relabel`; here `--near C`, `--near-m` and `--near-ramp-m`, applied to every
S); the bar still
judges the policy's R² against the paper's own labels (S = 1). Two things decide that R², and
this script separates them on one split:

- the law's own distance from the paper's: the R² per axis that the exact S law (a perfect
  student) scores against the stored labels, for every S in --scales;
- each policy's error: its R² against the stored labels and against each S law's labels (the
  S it was trained on is where it scores best).

Prints a line per law and per policy and writes JSON (default
benchmarks/results/cautious_law_fit.json). One torch thread; about a minute per d4 policy on the
quick preset's 8,082 test samples.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report
from command_shrinkage import policy_answers

from sim_harness.dataset.spec import DatasetSpec
from sim_harness.dataset.store import open_dataset
from sim_harness.experiments.machine import machine
from sim_harness.learning.evaluate import regression_metrics
from sim_harness.learning.relabel import NEAR_M, RAMP_M, cautious_targets


def r2_per_axis(pred: np.ndarray, target: np.ndarray) -> dict[str, float | None]:
    """R² of each body axis (x, y, z) of `pred` against `target`."""
    axes = regression_metrics(pred, target)["per_axis"]
    return {axis: axes[axis]["r2"] for axis in ("x", "y", "z")}


def show(r2: dict[str, float | None]) -> str:
    return " / ".join("n/a" if v is None else f"{v:.3f}" for v in r2.values())


def parse_scales(text: str) -> list[float]:
    try:
        scales = [float(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"--scales: expected numbers separated by commas, got {text!r}") from None
    if not scales or any(not 0.5 <= s <= 2.0 for s in scales):
        raise SystemExit(f"--scales: each S must be in [0.5, 2.0], got {text!r}")
    return scales


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, required=True, help="a recorded dataset")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--scales", default="1.1,1.15,1.2", help="separation scales S")
    parser.add_argument(
        "--near", type=float, default=1.0, help="close-range boost C of every law (default 1)"
    )
    parser.add_argument(
        "--near-m", type=float, default=NEAR_M, help=f"the boost's reach, m (default {NEAR_M})"
    )
    parser.add_argument(
        "--near-ramp-m",
        type=float,
        default=RAMP_M,
        help="the boost ramps in over this many metres inside its reach (default 0: a step)",
    )
    parser.add_argument(
        "--scale-reach-m",
        type=float,
        default=None,
        help="k_sep x S for the neighbours within this many metres only (default: every one)",
    )
    parser.add_argument("--model", type=Path, action="append", default=[], help="repeatable")
    parser.add_argument("--out", type=Path, default=RESULTS / "cautious_law_fit.json")
    args = parser.parse_args()
    scales = parse_scales(args.scales)
    dataset = open_dataset(args.dataset)
    split = dataset.split(args.split)
    params = DatasetSpec.from_dict(dataset.manifest["spec"]).flocking
    stored = np.asarray(split.targets, dtype=np.float64)
    if not 0.5 <= args.near <= 4.0:
        raise SystemExit(f"--near: C must be in [0.5, 4], got {args.near:g}")
    if not 0.5 <= args.near_m <= 5.0:
        raise SystemExit(f"--near-m: must be in [0.5, 5] m, got {args.near_m:g}")
    if not 0.0 <= args.near_ramp_m < args.near_m:
        raise SystemExit(f"--near-ramp-m: must be in [0, --near-m), got {args.near_ramp_m:g}")
    suffix = "" if args.near == 1.0 else f"+near{args.near:g}"
    if args.near != 1.0 and args.near_m != NEAR_M:
        suffix += f"@{args.near_m:g}m"
    if args.near != 1.0 and args.near_ramp_m > 0.0:
        suffix += f"~ramp{args.near_ramp_m:g}m"
    if args.scale_reach_m is not None:
        if args.scale_reach_m < args.near_m:
            raise SystemExit("--scale-reach-m: must reach at least --near-m")
        suffix += f" within {args.scale_reach_m:g}m"
    laws = {
        f"{s:g}{suffix}": cautious_targets(
            stored,
            split.meta,
            s,
            params,
            what=str(args.dataset),
            near_scale=args.near,
            near_m=args.near_m,
            ramp_m=args.near_ramp_m,
            reach_m=args.scale_reach_m,
        ).astype(np.float64)
        for s in scales
    }
    report: dict[str, Any] = {
        "dataset": str(args.dataset),
        "split": args.split,
        "samples": len(stored),
        "laws": {},
        "policies": {},
        "machine": machine(),
    }
    for s, labels in laws.items():
        r2 = r2_per_axis(labels, stored)
        report["laws"][s] = {"r2_vs_paper": r2}
        print(f"exact law k_sep x {s}: R² against the paper's labels {show(r2)}", flush=True)
    if args.model:
        images = np.array(split.images)  # a writable copy (the split may be memory-mapped)
    for model in args.model:
        answer = policy_answers(model, images)
        entry = {"r2_vs_paper": r2_per_axis(answer, stored)}
        entry.update({f"r2_vs_law_{s}": r2_per_axis(answer, lab) for s, lab in laws.items()})
        report["policies"][str(model)] = entry
        against = "; ".join(f"law x {s} {show(entry[f'r2_vs_law_{s}'])}" for s in laws)
        print(f"{model}: paper {show(entry['r2_vs_paper'])}; {against}", flush=True)
    write_report(report, args.out)


if __name__ == "__main__":
    main()
