"""Real PX4 SITL tests: a package, so that its conftest's PX4 instances stop after its last test."""
