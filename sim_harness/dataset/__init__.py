"""The paper's dataset: random linear flights, six-camera images, body-frame teacher targets.

`spec` (parameters and presets), `runs` (one run simulated), `store` (the on-disk format and the
reader), `generate` (parallel, resumable, deterministic generation and merging), `inspect`.
May import `sim_harness.sim` and `companion`'s contracts (aggregation, which flies the CNN, is in
`experiments`).
"""
