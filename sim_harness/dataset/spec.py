"""Dataset parameters (the paper's by default), presets, and the per-run random streams.

Generation as in the paper (SPEC.md, "Dataset generation"): N agents spawn in a 4 m cube, pairwise
>= 1.5 m apart; each follows its own constant velocity command drawn uniformly inside a unit cone
(length `cone_length_mps`, half-angle `cone_half_angle_deg`) whose axis points from the spawn centre
to the run's migration point; every 0.1 s every agent records its image and the teacher's Reynolds
command rotated into its body frame. A run ends when an agent comes within 1 m of the migration
point (arrival), a pair is closer than 1 m (collision) or farther than 7 m (dispersion).

Choices the paper leaves open, fixed here and recorded in every manifest:
- the migration point lies `migration_distance_m` from the spawn centre at its altitude, in a
  direction drawn uniformly per run (the targets are body-frame, so headings vary freely);
- the velocity commands are flown through the PX4-like vehicle model from rest, each drone starting
  with its heading along its command, so attitudes and camera tilts are realistic;
- a step whose state already meets a termination rule records no samples; a run also ends below
  `min_altitude_m` (ground) or after `max_run_s` (time limit);
- runs are independent: run k of split s draws everything from SeedSequence([seed, s, k]).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.flocking import FlockingParams
from companion.validation import require_int_range, require_positive, require_range
from sim_harness.errors import ConfigError
from sim_harness.sim.renderers import DEFAULT_RENDERER, require_renderer
from sim_harness.sim.world import SimRates

SPLITS: tuple[str, ...] = ("train", "val", "test")
COMPRESSIONS: tuple[str, ...] = ("deflate", "none")  # zip deflate level 1, or stored
TERMINATIONS: tuple[str, ...] = ("arrival", "collision", "dispersion", "ground", "time_limit")

# Sample counts per split, and other overrides: "smoke" cuts runs at 2 s so that it takes seconds.
PRESETS: dict[str, dict[str, Any]] = {
    "smoke": {"train_samples": 300, "val_samples": 100, "test_samples": 100, "max_run_s": 2.0},
    "quick": {"train_samples": 60_000, "val_samples": 8_000, "test_samples": 8_000},
    "paper": {"train_samples": 500_000, "val_samples": 60_000, "test_samples": 60_000},
}


@dataclass(frozen=True)
class DatasetSpec:
    """Everything that determines a dataset's content. Sizes are minimum sample counts per split."""

    train_samples: int = 60_000
    val_samples: int = 8_000
    test_samples: int = 8_000
    seed: int = 0
    n_agents: int = 9
    spawn_center_m: tuple[float, float, float] = (0.0, 0.0, 5.0)
    spawn_side_m: float = 4.0
    spawn_min_separation_m: float = 1.5
    cone_half_angle_deg: float = 15.0
    cone_length_mps: float = 1.0
    migration_distance_m: float = 30.0
    arrival_radius_m: float = 1.0
    collision_m: float = 1.0
    dispersion_m: float = 7.0
    min_altitude_m: float = 0.5
    max_run_s: float = 60.0
    flocking: FlockingParams = field(default_factory=FlockingParams)
    physics_hz: int = 100
    control_hz: int = 10  # = the camera rate: one sample per agent per control step
    shard_index: int = 0
    shard_count: int = 1
    renderer: str = DEFAULT_RENDERER  # what draws the images (sim_harness.sim.renderers)
    compression: str = "deflate"  # run files: "deflate" (half the disk) or "none" (fastest)

    def __post_init__(self) -> None:
        for split in SPLITS:
            require_int_range(f"dataset.{split}_samples", getattr(self, f"{split}_samples"), 1)
        require_int_range("dataset.seed", self.seed, 0)
        require_int_range("dataset.n_agents", self.n_agents, 2, 200)
        require_positive("dataset.spawn_side_m", self.spawn_side_m)
        require_range("dataset.cone_half_angle_deg", self.cone_half_angle_deg, 0.0, 90.0)
        require_positive("dataset.cone_length_mps", self.cone_length_mps)
        for name in ("migration_distance_m", "arrival_radius_m", "collision_m", "max_run_s"):
            require_positive(f"dataset.{name}", getattr(self, name))
        if self.dispersion_m <= self.collision_m:
            raise ConfigError(
                f"dataset.dispersion_m must be > dataset.collision_m ({self.collision_m:g} m), "
                f"got {self.dispersion_m:g}"
            )
        require_int_range("dataset.shard_count", self.shard_count, 1)
        require_int_range("dataset.shard_index", self.shard_index, 0, self.shard_count - 1)
        SimRates(self.physics_hz, self.control_hz)  # validates divisibility
        require_renderer(self.renderer, "dataset.renderer")
        if self.compression not in COMPRESSIONS:
            raise ConfigError(
                f"dataset.compression: {self.compression!r} must be one of "
                + ", ".join(COMPRESSIONS)
            )

    @property
    def rates(self) -> SimRates:
        return SimRates(self.physics_hz, self.control_hz)

    def target(self, split: str) -> int:
        """Minimum number of samples of `split`."""
        return int(getattr(self, f"{split}_samples"))

    def run_index(self, split: str, k: int) -> int:
        """Global index of this shard's k-th run of `split` (shards interleave)."""
        del split
        return self.shard_index + k * self.shard_count

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def content_dict(self) -> dict[str, Any]:
        """The parameters that decide what a run contains (not how many runs, not the shard)."""
        d = self.as_dict()
        for key in ("train_samples", "val_samples", "test_samples", "shard_index", "shard_count"):
            d.pop(key)
        if d["renderer"] == DEFAULT_RENDERER:  # ids of datasets made before the choice existed
            d.pop("renderer")
        d.pop("compression")  # how the runs are stored, not what they hold
        return d

    def content_id(self) -> str:
        """Short hash of `content_dict`: datasets with equal ids have identical runs."""
        text = json.dumps(self.content_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DatasetSpec:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"dataset: unknown parameter(s) {', '.join(unknown)}")
        values = dict(d)
        if "flocking" in values and isinstance(values["flocking"], dict):
            values["flocking"] = FlockingParams(**values["flocking"])
        if "spawn_center_m" in values:
            values["spawn_center_m"] = tuple(values["spawn_center_m"])
        return cls(**values)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> DatasetSpec:
        if name not in PRESETS:
            raise ConfigError(f"dataset.preset must be one of {', '.join(PRESETS)}, got {name!r}")
        return cls(**{**PRESETS[name], **overrides})


def run_rng(spec: DatasetSpec, split: str, run_index: int) -> np.random.Generator:
    """The random stream of one run: independent of every other run, worker and shard."""
    return np.random.default_rng(
        np.random.SeedSequence([spec.seed, SPLITS.index(split), run_index])
    )


def sample_in_cone(
    rng: np.random.Generator, n: int, axis: np.ndarray, half_angle_rad: float, length: float
) -> np.ndarray:
    """N points uniform in the solid cone with apex 0, unit `axis`, height `length`: (N, 3).

    Uniform in volume: height h = length * U^(1/3), radius r = h tan(a) sqrt(V), angle uniform.
    """
    axis = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    h = length * rng.random(n) ** (1.0 / 3.0)
    r = h * np.tan(half_angle_rad) * np.sqrt(rng.random(n))
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    return h[:, None] * axis + (r * np.cos(phi))[:, None] * e1 + (r * np.sin(phi))[:, None] * e2
