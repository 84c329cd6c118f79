"""Example fault plans for `swarm-sim hil --faults` (TOML files next to this module)."""

from pathlib import Path

PLANS_DIR = Path(__file__).resolve().parent
