"""`swarm-sim`: fly scenarios in the pybullet harness and write the paper's figures.

    swarm-sim demo                       # the main job: 9 drones, shipped CNN vs teacher, report
    swarm-sim experiments --suite paper|generalization|bar --seeds 5 --model M --out DIR
    swarm-sim compare runs/a runs/b                 # two reports of the same seeds, seed by seed
    swarm-sim fly --scenario common --agents 9 --seed 0 --out runs/common
    swarm-sim view --scenario common --seed 0 --step 20 --agent 0   # what one drone sees
    swarm-sim dataset generate --preset quick          # the paper's dataset (resumable)
    swarm-sim dataset inspect data/quick-s0
    swarm-sim hil --agents 3 --compare                # the real daemons fly the swarm

Errors are printed as one line on stderr with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from companion.errors import CompanionError
from sim_harness.dataset.cli import add_dataset_commands
from sim_harness.experiments.cli import add_aggregate_command, add_experiment_commands
from sim_harness.experiments.compare import add_compare_command
from sim_harness.hil.cli import add_hil_commands
from sim_harness.learning.cli import add_learning_commands
from sim_harness.sim.cli import add_sim_commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="swarm-sim", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    add_sim_commands(sub)
    add_experiment_commands(sub)
    add_compare_command(sub)
    add_aggregate_command(add_dataset_commands(sub))
    add_learning_commands(sub)
    add_hil_commands(sub)
    return parser


def run(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.handler(args))


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return run(argv)
    except CompanionError as exc:
        print(f"swarm-sim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("swarm-sim: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
