"""Experiments: the CNN flying the swarm, suites and their statistics, reports, DAgger rounds.

May import `learning`, `dataset`, `sim` and `companion`; `hil` and the CLI sit above it.
"""
