"""Attitude history (attitude at capture time) and the NED -> ENU pose the control law gets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion import frames
from companion.autopilot_types import AutopilotTelemetry, Stamped
from companion.pose_history import AttitudeHistory, pose_enu


def q_ned_yaw(yaw_ned_rad: float) -> np.ndarray:
    """A level attitude facing `yaw_ned_rad` (0 north, clockwise), PX4's NED <- FRD."""
    return np.array([math.cos(yaw_ned_rad / 2), 0.0, 0.0, math.sin(yaw_ned_rad / 2)])


def yaw_enu_of(q_enu_flu: np.ndarray) -> float:
    return float(frames.euler_zyx_from_quat(q_enu_flu)[2])


def test_nearest_sample_within_the_gap() -> None:
    history = AttitudeHistory()
    for t_s, yaw_ned in ((1.0, 0.0), (1.1, 0.5), (1.2, 1.0)):
        assert history.add_ned_frd(t_s, q_ned_yaw(yaw_ned))
    # NED yaw 0.5 (east of north) is ENU yaw pi/2 - 0.5.
    assert yaw_enu_of(history.at(1.12, 0.05)) == pytest.approx(math.pi / 2 - 0.5)
    assert yaw_enu_of(history.at(1.17, 0.05)) == pytest.approx(math.pi / 2 - 1.0)
    assert yaw_enu_of(history.at(0.98, 0.05)) == pytest.approx(math.pi / 2)
    assert history.at(1.3, 0.05) is None  # nothing that recent
    assert history.at(0.5, 0.05) is None  # nothing that old


def test_out_of_order_and_invalid_samples_are_ignored() -> None:
    history = AttitudeHistory(capacity=3)
    assert history.add_ned_frd(1.0, q_ned_yaw(0.0))
    assert not history.add_ned_frd(1.0, q_ned_yaw(1.0))  # same stamp: not new
    assert not history.add_ned_frd(0.9, q_ned_yaw(1.0))
    assert not history.add_ned_frd(1.1, np.full(4, np.nan))  # MAVSDK's "no data yet"
    assert not history.add_ned_frd(1.1, np.zeros(4))
    for t_s in (1.1, 1.2, 1.3):
        history.add_ned_frd(t_s, q_ned_yaw(0.0))
    assert len(history) == 3 and history.at(1.0, 0.05) is None  # oldest dropped


def test_add_from_telemetry_skips_missing_attitude() -> None:
    history = AttitudeHistory()
    assert not history.add_from(AutopilotTelemetry())
    telemetry = AutopilotTelemetry(q_ned_frd_wxyz=Stamped(q_ned_yaw(0.0), 2.0))
    assert history.add_from(telemetry) and not history.add_from(telemetry)


def test_pose_enu_converts_frames_and_drops_stale_values() -> None:
    telemetry = AutopilotTelemetry(
        position_ned_m=Stamped(np.array([1.0, 2.0, -5.0]), 10.0),
        q_ned_frd_wxyz=Stamped(q_ned_yaw(math.pi / 2), 10.0),  # facing east
    )
    pos, yaw = pose_enu(telemetry, now_s=10.2, max_age_s=0.5)
    np.testing.assert_allclose(pos, [2.0, 1.0, 5.0])  # east, north, up
    assert yaw == pytest.approx(0.0, abs=1e-12)  # ENU yaw 0 = east
    pos, yaw = pose_enu(telemetry, now_s=10.6, max_age_s=0.5)
    assert np.all(np.isnan(pos)) and math.isnan(yaw)
    pos, yaw = pose_enu(AutopilotTelemetry(), now_s=0.0, max_age_s=0.5)
    assert np.all(np.isnan(pos)) and math.isnan(yaw)


@pytest.mark.parametrize("seed", range(5))
def test_pose_enu_yaw_agrees_with_the_frame_conventions(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q_ned_frd = frames.quat_normalize(rng.normal(size=4))
    telemetry = AutopilotTelemetry(q_ned_frd_wxyz=Stamped(q_ned_frd, 0.0))
    _, yaw = pose_enu(telemetry, now_s=0.0, max_age_s=1.0)
    q_enu_flu = frames.quat_ned_frd_to_enu_flu(q_ned_frd)
    assert yaw == pytest.approx(yaw_enu_of(q_enu_flu), abs=1e-9)
    # ...and the history hands out the same attitude, converted.
    history = AttitudeHistory()
    history.add_ned_frd(0.0, q_ned_frd)
    np.testing.assert_allclose(history.at(0.0, 0.1), q_enu_flu, atol=1e-12)


# --- boundaries: exactly at each limit and one float step either side ------------------------
# 10.5 - 10.0 == 0.5 exactly; math.nextafter moves the sample time by the smallest step there is.
MAX_AGE_S = 0.5


@pytest.mark.parametrize(
    ("stamp_s", "fresh"),
    [
        (math.nextafter(10.0, math.inf), True),  # one step younger than max_age_s
        (10.0, True),  # exactly max_age_s old: the limit is inclusive
        (math.nextafter(10.0, -math.inf), False),  # one step older: NaN (a hover)
    ],
)
def test_pose_enu_age_limit_to_the_last_step(stamp_s: float, fresh: bool) -> None:
    now_s = 10.0 + MAX_AGE_S
    assert now_s - 10.0 == MAX_AGE_S  # the arithmetic really is exact
    telemetry = AutopilotTelemetry(
        position_ned_m=Stamped(np.array([1.0, 2.0, -5.0]), stamp_s),
        q_ned_frd_wxyz=Stamped(q_ned_yaw(math.pi / 2), stamp_s),
    )
    pos, yaw = pose_enu(telemetry, now_s=now_s, max_age_s=MAX_AGE_S)
    assert bool(np.all(np.isfinite(pos))) is fresh  # position and attitude judged alike
    assert math.isfinite(yaw) is fresh


@pytest.mark.parametrize(
    ("t_s", "found"),
    [
        (math.nextafter(10.5, -math.inf), True),  # one step inside max_gap_s of the sample
        (10.5, True),  # exactly max_gap_s away: the limit is inclusive
        (math.nextafter(10.5, math.inf), False),  # one step further: no attitude
        (9.5, True),  # the same on the other side
        (math.nextafter(9.5, -math.inf), False),
    ],
)
def test_attitude_gap_limit_to_the_last_step(t_s: float, found: bool) -> None:
    history = AttitudeHistory()
    history.add_ned_frd(10.0, q_ned_yaw(0.0))
    assert (history.at(t_s, MAX_AGE_S) is not None) is found
