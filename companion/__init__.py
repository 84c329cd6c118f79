"""Onboard companion for vision-based drone swarms.

The pure core (flocking law, frame conventions) is shared with the simulation harness; nothing here
imports pybullet, matplotlib, pymavlink or `sim_harness`.
"""

__version__ = "0.1.0"
