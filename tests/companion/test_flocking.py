"""The paper's flocking law: hand-computed cases, perception radius, degenerate cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.flocking import (
    COINCIDENT_M,
    FlockingParams,
    cap_speed,
    flocking_command,
    migration_velocity,
    pairwise_offsets,
    reynolds_from_offsets,
)

TOL = 1e-9
DEFAULT = FlockingParams()


def assert_vec(actual: np.ndarray, expected: object, tol: float = TOL) -> None:
    np.testing.assert_allclose(actual, np.asarray(expected, dtype=float), rtol=0.0, atol=tol)


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


def test_defaults_are_the_papers_values() -> None:
    assert DEFAULT.k_sep == 7.0
    assert DEFAULT.k_coh == 1.0
    assert DEFAULT.k_mig == 1.0
    assert DEFAULT.r_max_m == 20.0
    assert DEFAULT.v_max_mps == 2.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"k_sep": -1.0}, "flocking.k_sep"),
        ({"k_coh": -0.1}, "flocking.k_coh"),
        ({"k_mig": -2.0}, "flocking.k_mig"),
        ({"v_max_mps": 0.0}, "flocking.v_max_mps"),
        ({"v_max_mps": -1.0}, "flocking.v_max_mps"),
        ({"r_max_m": 0.0}, "flocking.r_max_m"),
        ({"r_max_m": -5.0}, "flocking.r_max_m"),
        ({"k_sep": math.nan}, "flocking.k_sep"),
        ({"k_coh": math.nan}, "flocking.k_coh"),
        ({"k_mig": math.inf}, "flocking.k_mig"),
        ({"v_max_mps": math.nan}, "flocking.v_max_mps"),
        ({"r_max_m": math.nan}, "flocking.r_max_m"),
        ({"r_max_m": math.inf}, "flocking.r_max_m"),
    ],
)
def test_invalid_params_raise_config_error_naming_the_field(
    kwargs: dict[str, float], field: str
) -> None:
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        FlockingParams(**kwargs)


def test_config_error_is_a_value_error() -> None:
    with pytest.raises(ValueError):
        FlockingParams(k_sep=-1.0)


def test_zero_gains_are_allowed() -> None:
    params = FlockingParams(k_sep=0.0, k_coh=0.0, k_mig=0.0)
    cmd = flocking_command([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [0.0, 10.0, 0.0], params)
    assert_vec(cmd.final, np.zeros((2, 3)))


# --------------------------------------------------------------------------------------------
# Hand-computed cases (default params: k_sep=7, k_coh=1, k_mig=1, r_max=20, v_max=2)
# --------------------------------------------------------------------------------------------


def test_two_agents_hand_computed() -> None:
    cmd = flocking_command([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], None, DEFAULT)
    # Agent 0: r_01 = (2,0,0), |r|^2 = 4, |N| = 1.
    #   sep = -7/1 * (2,0,0)/4 = (-3.5, 0, 0); coh = 1/1 * (2,0,0) = (2, 0, 0)
    #   rey = (-3.5 + 2, 0, 0) = (-1.5, 0, 0); |rey| = 1.5 < 2 so final = rey.
    # Agent 1 is the mirror image: r_10 = (-2,0,0).
    assert_vec(cmd.separation, [[-3.5, 0.0, 0.0], [3.5, 0.0, 0.0]])
    assert_vec(cmd.cohesion, [[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    assert_vec(cmd.reynolds, [[-1.5, 0.0, 0.0], [1.5, 0.0, 0.0]])
    assert_vec(cmd.migration, np.zeros((2, 3)))
    assert_vec(cmd.final, [[-1.5, 0.0, 0.0], [1.5, 0.0, 0.0]])
    assert cmd.n_neighbours.tolist() == [1, 1]


def test_two_agents_far_apart_attract() -> None:
    cmd = flocking_command([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]], None, DEFAULT)
    # Agent 0: sep = -7 * (10,0,0)/100 = (-0.7,0,0); coh = (10,0,0); rey = (9.3,0,0)
    # |rey| = 9.3 > 2: final = (2,0,0).
    assert_vec(cmd.separation[0], [-0.7, 0.0, 0.0])
    assert_vec(cmd.cohesion[0], [10.0, 0.0, 0.0])
    assert_vec(cmd.reynolds[0], [9.3, 0.0, 0.0])
    assert_vec(cmd.final, [[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])


def test_three_agents_non_collinear_hand_computed() -> None:
    positions = [[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]]
    cmd = flocking_command(positions, None, DEFAULT)
    # Agent 0: r_01 = (3,0,0) (|r|^2 = 9), r_02 = (0,4,0) (|r|^2 = 16), |N| = 2
    #   sum r/|r|^2 = (3/9, 4/16, 0) = (1/3, 1/4, 0)
    #   sep = -7/2 * (1/3, 1/4, 0) = (-7/6, -7/8, 0)
    #   coh = 1/2 * (3, 4, 0) = (1.5, 2, 0)
    #   rey = (1.5 - 7/6, 2 - 7/8, 0) = (1/3, 9/8, 0)
    # Agent 1: r_10 = (-3,0,0) (9), r_12 = (-3,4,0) (25)
    #   sum = (-3/9 - 3/25, 4/25, 0) = (-34/75, 4/25, 0)
    #   sep = -7/2 * sum = (119/75, -14/25, 0)
    #   coh = 1/2 * (-6, 4, 0) = (-3, 2, 0)
    #   rey = (119/75 - 3, 2 - 14/25, 0) = (-106/75, 36/25, 0)
    # Agent 2: r_20 = (0,-4,0) (16), r_21 = (3,-4,0) (25)
    #   sum = (3/25, -4/16 - 4/25, 0) = (3/25, -41/100, 0)
    #   sep = -7/2 * sum = (-21/50, 287/200, 0)
    #   coh = 1/2 * (3, -8, 0) = (1.5, -4, 0)
    #   rey = (1.5 - 21/50, -4 + 287/200, 0) = (27/25, -513/200, 0)
    assert_vec(
        cmd.separation,
        [[-7 / 6, -7 / 8, 0.0], [119 / 75, -14 / 25, 0.0], [-21 / 50, 287 / 200, 0.0]],
    )
    assert_vec(cmd.cohesion, [[1.5, 2.0, 0.0], [-3.0, 2.0, 0.0], [1.5, -4.0, 0.0]])
    rey = [[1 / 3, 9 / 8, 0.0], [-106 / 75, 36 / 25, 0.0], [27 / 25, -513 / 200, 0.0]]
    assert_vec(cmd.reynolds, rey)
    assert cmd.n_neighbours.tolist() == [2, 2, 2]
    # Speed cap at 2 m/s:
    #   |rey_0| = sqrt(1/9 + 81/64) ~ 1.173 < 2: unchanged
    #   |rey_1| = sqrt((106/75)^2 + (36/25)^2) ~ 2.018 > 2: scaled to norm 2
    #   |rey_2| = sqrt((27/25)^2 + (513/200)^2) ~ 2.783 > 2: scaled to norm 2
    n1 = math.sqrt((106 / 75) ** 2 + (36 / 25) ** 2)
    n2 = math.sqrt((27 / 25) ** 2 + (513 / 200) ** 2)
    assert n1 > 2.0
    assert n2 > 2.0
    final = [
        rey[0],
        [-106 / 75 * 2 / n1, 36 / 25 * 2 / n1, 0.0],
        [27 / 25 * 2 / n2, -513 / 200 * 2 / n2, 0.0],
    ]
    assert_vec(cmd.final, final)


def test_migration_term_hand_computed() -> None:
    # Agent at (1,2,3), point (4,6,3): r_mig = (3,4,0), |r_mig| = 5, k_mig = 1 -> (0.6, 0.8, 0)
    # Agent at (0,0,0), point (0,0,-2): unit (0,0,-1), times k_mig = 2.5 -> (0, 0, -2.5)
    mig = migration_velocity(
        [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], [[4.0, 6.0, 3.0], [0.0, 0.0, -2.0]], 2.5
    )
    assert_vec(mig, [[0.6 * 2.5, 0.8 * 2.5, 0.0], [0.0, 0.0, -2.5]])


def test_full_command_with_common_migration_point() -> None:
    cmd = flocking_command([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [0.0, 10.0, 0.0], DEFAULT)
    # Agent 0: r_mig = (0,10,0) -> mig = (0,1,0); v~ = (-1.5, 1, 0), |v~| = sqrt(3.25) < 2
    # Agent 1: r_mig = (-2,10,0), |r_mig| = sqrt(104) -> mig = (-2, 10, 0)/sqrt(104)
    #   v~ = (1.5 - 2/sqrt(104), 10/sqrt(104), 0), |v~| ~ 1.63 < 2
    s = math.sqrt(104.0)
    assert_vec(cmd.migration, [[0.0, 1.0, 0.0], [-2 / s, 10 / s, 0.0]])
    assert_vec(cmd.final, [[-1.5, 1.0, 0.0], [1.5 - 2 / s, 10 / s, 0.0]])


def test_migration_with_large_gain_is_capped_in_its_direction() -> None:
    params = FlockingParams(k_mig=5.0)
    cmd = flocking_command([[0.0, 0.0, 0.0]], [[0.0, 0.0, 7.0]], params)
    # Single agent: rey = 0, mig = 5 * (0,0,1) = (0,0,5); capped to (0,0,2).
    assert_vec(cmd.reynolds, [[0.0, 0.0, 0.0]])
    assert_vec(cmd.migration, [[0.0, 0.0, 5.0]])
    assert_vec(cmd.final, [[0.0, 0.0, 2.0]])


def test_cap_speed_above_limit_keeps_direction_and_sets_norm() -> None:
    # (3,4,0) has norm 5 > 2: scaled by 2/5 -> (1.2, 1.6, 0)
    assert_vec(cap_speed([3.0, 4.0, 0.0], 2.0), [1.2, 1.6, 0.0])
    # (0,-6,8) norm 10 > 4: (0, -2.4, 3.2)
    assert_vec(cap_speed([[0.0, -6.0, 8.0]], 4.0), [[0.0, -2.4, 3.2]])


def test_cap_speed_below_or_at_limit_is_untouched() -> None:
    v = np.array([[0.3, 0.4, 0.0], [1.2, 1.6, 0.0], [0.0, 0.0, -1.9]])
    np.testing.assert_array_equal(cap_speed(v, 2.0), v)


def test_cap_speed_zero_stays_zero() -> None:
    np.testing.assert_array_equal(cap_speed(np.zeros((4, 3)), 2.0), np.zeros((4, 3)))


def test_cap_speed_handles_time_and_agent_axes() -> None:
    v = np.array([[[3.0, 4.0, 0.0], [0.1, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]]])
    out = cap_speed(v, 2.0)
    assert out.shape == (2, 2, 3)
    assert_vec(out, [[[1.2, 1.6, 0.0], [0.1, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]]])


# --------------------------------------------------------------------------------------------
# Perception radius
# --------------------------------------------------------------------------------------------


def test_agent_beyond_r_max_changes_nothing() -> None:
    pair = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    base = flocking_command(pair, None, DEFAULT)
    # Third agent at (0,0,25): 25 m from agent 0, sqrt(4 + 625) ~ 25.08 m from agent 1.
    cmd = flocking_command([*pair, [0.0, 0.0, 25.0]], None, DEFAULT)
    np.testing.assert_array_equal(cmd.reynolds[:2], base.reynolds)
    np.testing.assert_array_equal(cmd.final[:2], base.final)
    assert cmd.n_neighbours.tolist() == [1, 1, 0]
    # The lone agent has no neighbours: zero Reynolds command.
    assert_vec(cmd.separation[2], [0.0, 0.0, 0.0])
    assert_vec(cmd.cohesion[2], [0.0, 0.0, 0.0])
    assert_vec(cmd.reynolds[2], [0.0, 0.0, 0.0])
    assert_vec(cmd.final[2], [0.0, 0.0, 0.0])


def test_agent_exactly_at_r_max_is_not_a_neighbour() -> None:
    # Distance exactly 20 m: the neighbour test is strict (|r| < r_max).
    cmd = flocking_command([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0]], None, DEFAULT)
    assert cmd.n_neighbours.tolist() == [0, 0]
    np.testing.assert_array_equal(cmd.reynolds, np.zeros((2, 3)))
    # Just inside: it is a neighbour. sep = -7 * (19.5,0,0)/19.5^2 = (-7/19.5, 0, 0)
    cmd = flocking_command([[0.0, 0.0, 0.0], [19.5, 0.0, 0.0]], None, DEFAULT)
    assert cmd.n_neighbours.tolist() == [1, 1]
    assert_vec(cmd.separation[0], [-7 / 19.5, 0.0, 0.0])
    assert_vec(cmd.cohesion[0], [19.5, 0.0, 0.0])


def test_third_agent_exactly_at_r_max_changes_nothing() -> None:
    pair = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    base = flocking_command(pair, None, DEFAULT)
    # (0,20,0): exactly 20 m from agent 0, sqrt(404) m from agent 1.
    cmd = flocking_command([*pair, [0.0, 20.0, 0.0]], None, DEFAULT)
    np.testing.assert_array_equal(cmd.reynolds[:2], base.reynolds)
    assert cmd.n_neighbours.tolist() == [1, 1, 0]


def test_custom_r_max() -> None:
    params = FlockingParams(r_max_m=3.0)
    # Agents on a line at 0, 2, 5: 0-1 at 2 m (in), 1-2 at 3 m (out: strict), 0-2 at 5 m (out).
    cmd = flocking_command([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [5.0, 0.0, 0.0]], None, params)
    assert cmd.n_neighbours.tolist() == [1, 1, 0]
    assert_vec(cmd.reynolds, [[-1.5, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 0.0, 0.0]])


def test_single_agent_has_zero_reynolds() -> None:
    cmd = flocking_command([[1.0, 2.0, 3.0]], None, DEFAULT)
    assert cmd.n_neighbours.tolist() == [0]
    np.testing.assert_array_equal(cmd.reynolds, np.zeros((1, 3)))
    np.testing.assert_array_equal(cmd.final, np.zeros((1, 3)))


# --------------------------------------------------------------------------------------------
# Degenerate cases
# --------------------------------------------------------------------------------------------


def test_coincident_neighbour_counts_but_adds_no_separation() -> None:
    positions = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    cmd = flocking_command(positions, None, DEFAULT)
    # Agent 0: neighbours 1 (coincident) and 2, |N| = 2.
    #   sep = -7/2 * (2,0,0)/4 = (-1.75, 0, 0) (agent 1 adds nothing)
    #   coh = 1/2 * ((0,0,0) + (2,0,0)) = (1, 0, 0)
    # Agent 2: r_20 = r_21 = (-2,0,0), |N| = 2
    #   sep = -7/2 * 2 * (-2,0,0)/4 = (3.5, 0, 0); coh = 1/2 * (-4,0,0) = (-2, 0, 0)
    assert cmd.n_neighbours.tolist() == [2, 2, 2]
    assert_vec(cmd.separation, [[-1.75, 0.0, 0.0], [-1.75, 0.0, 0.0], [3.5, 0.0, 0.0]])
    assert_vec(cmd.cohesion, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    assert_vec(cmd.reynolds, [[-0.75, 0.0, 0.0], [-0.75, 0.0, 0.0], [1.5, 0.0, 0.0]])
    for part in (cmd.separation, cmd.cohesion, cmd.reynolds, cmd.migration, cmd.final):
        assert np.all(np.isfinite(part))


def test_two_coincident_agents_get_zero_finite_command() -> None:
    cmd = flocking_command([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]], [5.0, 1.0, 1.0], DEFAULT)
    assert cmd.n_neighbours.tolist() == [1, 1]
    np.testing.assert_array_equal(cmd.reynolds, np.zeros((2, 3)))
    assert_vec(cmd.final, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def test_nearly_coincident_below_threshold_is_treated_as_coincident() -> None:
    eps = COINCIDENT_M / 10
    cmd = flocking_command([[0.0, 0.0, 0.0], [eps, 0.0, 0.0]], None, DEFAULT)
    assert np.all(np.isfinite(cmd.final))
    assert_vec(cmd.separation, np.zeros((2, 3)))


def test_agent_at_its_migration_point_gets_zero_migration() -> None:
    cmd = flocking_command(
        [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [2.0, 5.0, 0.0]], DEFAULT
    )
    # Agent 0 is at its point: no migration, final = rey = (-1.5, 0, 0).
    # Agent 1: unit (0,1,0); v~ = (1.5, 1, 0), |v~| < 2.
    assert_vec(cmd.migration, [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert_vec(cmd.final, [[-1.5, 0.0, 0.0], [1.5, 1.0, 0.0]])


def test_nan_migration_row_means_no_migration() -> None:
    points = np.array([[np.nan, np.nan, np.nan], [2.0, 5.0, 0.0]])
    cmd = flocking_command([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], points, DEFAULT)
    assert_vec(cmd.migration, [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert_vec(cmd.final, [[-1.5, 0.0, 0.0], [1.5, 1.0, 0.0]])


def test_partially_nan_migration_row_means_no_migration() -> None:
    mig = migration_velocity([[0.0, 0.0, 0.0]], [[1.0, np.nan, 0.0]], 1.0)
    np.testing.assert_array_equal(mig, np.zeros((1, 3)))


def test_common_migration_point_broadcasts() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [3.0, 1.0, -2.0], [-4.0, 2.0, 1.0]])
    point = np.array([10.0, -3.0, 4.0])
    common = flocking_command(positions, point, DEFAULT)
    repeated = flocking_command(positions, np.tile(point, (3, 1)), DEFAULT)
    for name in ("separation", "cohesion", "reynolds", "migration", "final"):
        np.testing.assert_array_equal(getattr(common, name), getattr(repeated, name))
    assert np.all(np.linalg.norm(common.migration, axis=1) == pytest.approx(1.0))


def test_no_migration_point() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [3.0, 1.0, -2.0], [-4.0, 2.0, 1.0]])
    cmd = flocking_command(positions, None, DEFAULT)
    np.testing.assert_array_equal(cmd.migration, np.zeros((3, 3)))
    np.testing.assert_array_equal(cmd.final, cap_speed(cmd.reynolds, DEFAULT.v_max_mps))
    np.testing.assert_array_equal(migration_velocity(positions, None, 1.0), np.zeros((3, 3)))


def test_positions_must_be_n_by_3() -> None:
    with pytest.raises(ValueError):
        flocking_command([0.0, 0.0, 0.0], None, DEFAULT)
    with pytest.raises(ValueError):
        flocking_command(np.zeros((3, 2)), None, DEFAULT)


def test_pairwise_offsets_convention() -> None:
    # r_ij = p_j - p_i
    r = pairwise_offsets([[1.0, 0.0, 0.0], [4.0, 2.0, -1.0]])
    assert r.shape == (2, 2, 3)
    assert_vec(r[0, 1], [3.0, 2.0, -1.0])
    assert_vec(r[1, 0], [-3.0, -2.0, 1.0])
    assert_vec(r[0, 0], [0.0, 0.0, 0.0])


def test_reynolds_from_offsets_ignores_padding() -> None:
    # Agent 0 perceives one neighbour at (2,0,0); the other two slots are padding.
    offsets = np.array([[[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [5.0, 5.0, 5.0]]])
    valid = np.array([[True, False, False]])
    sep, coh, count = reynolds_from_offsets(offsets, valid, DEFAULT)
    assert count.tolist() == [1]
    assert_vec(sep, [[-3.5, 0.0, 0.0]])
    assert_vec(coh, [[2.0, 0.0, 0.0]])


def test_invalid_slots_are_ignored_even_when_nan() -> None:
    # Agent 0 perceives one neighbour 2 m east; the second slot is NaN padding marked invalid.
    offsets = np.array([[[2.0, 0.0, 0.0], [np.nan, np.nan, np.nan]]])
    sep, coh, count = reynolds_from_offsets(offsets, np.array([[True, False]]), FlockingParams())
    np.testing.assert_allclose(sep, [[-3.5, 0.0, 0.0]], atol=1e-12)  # -7 * (2,0,0) / 2^2
    np.testing.assert_allclose(coh, [[2.0, 0.0, 0.0]], atol=1e-12)
    assert count.tolist() == [1]
