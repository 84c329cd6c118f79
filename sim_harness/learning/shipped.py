"""Where the shipped policy lives: `models/` of the checkout this package is installed from."""

from __future__ import annotations

from pathlib import Path

# The project root holds `models/` next to the `sim_harness` package (an editable install, as the
# README sets up), so the shipped model is found from any working folder.
PROJECT_ROOT = Path(__file__).resolve().parents[2]
SHIPPED_MODEL_PATH = PROJECT_ROOT / "models" / "swarm_cnn.pt"
