"""The ground and research side, CLI `swarm-sim`; its packages, lowest first:

`sim` (pybullet world, vehicles, rendering, scenarios, rollout, metrics) < `dataset` < `learning`
< `experiments` < `hil`; `errors` is shared and `cli` only dispatches. A package imports only
itself, the packages below it and `companion`'s contracts.
"""
