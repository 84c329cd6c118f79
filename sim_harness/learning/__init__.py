"""Learning: the DroNet-style network, training, checkpoints, evaluation, export, Grad-CAM.

May import `sim_harness.dataset`, `sim_harness.sim` and `companion`'s contracts; never
`experiments` or `hil`.
"""
