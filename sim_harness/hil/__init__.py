"""Hardware-in-the-loop: pty cameras, the PX4 emulator, and the harness flying real daemons.

May import `experiments`, `learning`, `dataset`, `sim` and `companion`; only the CLI sits above it.
"""
