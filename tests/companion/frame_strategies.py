"""Hypothesis strategies and comparisons shared by the frame-convention tests."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, settings
from hypothesis import strategies as st

from companion.frames import quat_to_rotmat

TOL = 1e-9
PROPERTY = settings(max_examples=50, deadline=None)

unit_interval = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)
coord = st.floats(-100.0, 100.0, allow_nan=False, allow_subnormal=False)
vector = st.tuples(coord, coord, coord).map(lambda v: np.array(v, dtype=float))


@st.composite
def quaternions(draw: st.DrawFn) -> np.ndarray:
    """Unit quaternions (w, x, y, z), any sign of w."""
    q = np.array([draw(unit_interval) for _ in range(4)])
    assume(np.linalg.norm(q) > 0.1)
    return q / np.linalg.norm(q)


@st.composite
def quaternion_batches(draw: st.DrawFn) -> np.ndarray:
    n = draw(st.integers(1, 5))
    return np.stack([draw(quaternions()) for _ in range(n)])


def angle_diff(a: float | np.ndarray, b: float | np.ndarray) -> np.ndarray:
    """Smallest signed difference between angles, robust to the +-pi seam."""
    d = np.asarray(a) - np.asarray(b)
    return np.arctan2(np.sin(d), np.cos(d))


def same_rotation_quat(a: np.ndarray, b: np.ndarray) -> bool:
    """q and -q are the same rotation."""
    return bool(min(np.max(np.abs(a - b)), np.max(np.abs(a + b))) < TOL)


def rot(q: np.ndarray) -> np.ndarray:
    return quat_to_rotmat(q)
