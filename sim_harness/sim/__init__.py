"""The simulator: pybullet world, vehicle model, scene and rendering, scenarios, rollout, metrics.

May import `companion`'s contracts and `sim_harness.errors` only: nothing here knows about
datasets, learning or experiments.
"""
