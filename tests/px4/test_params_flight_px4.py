"""The shipped parameter file in flight on real PX4 (SITL + SIH): PX4 flies the daemon's vertical
speed instead of clipping it (issue 19 finding 4: MPC_Z_VEL_MAX_UP 1.0 clipped -1.21 m/s NED to
-1.00), and a clean daemon exit ends in Hold with one "Connection to mission computer lost"
message COM_OBC_LOSS_T later and no action (issue 19 finding 7).

One daemon run (the unmodified `companion run`) on the vehicle with the file loaded, judged by
what PX4 reports on its GCS link: POSITION_TARGET_LOCAL_NED (the setpoint PX4 flies, after its
own caps), LOCAL_POSITION_NED, HEARTBEAT mode and armed flag, STATUSTEXT.
"""

from __future__ import annotations

import signal
import time
from typing import Any

from companion.param_check import read_params_file
from sim_harness.hil.px4_gcs import GroundStation
from sim_harness.hil.px4_logic import Px4Mode
from sim_harness.hil.px4_params import SHIPPED_PARAMS

CLIMB_BODY_FLU = (0.5, 0.0, 1.5)  # forward 0.5, up 1.5 m/s: 1.58 m/s in 3-D, under the 2 m/s cap
CLIMB_NED_MPS = -1.5
PARAMS = {row.name: row.value for row in read_params_file(SHIPPED_PARAMS)}
OBC_LOSS_T_S = PARAMS["COM_OBC_LOSS_T"]
ENGAGE_GUARD_S = 40.0  # start-up (torch, MAVSDK, health) + pre-stream; ~5-8 s here
HEARTBEAT_SLACK_S = 1.3  # PX4's heartbeat is 1 Hz on the GCS link


def mean_vz_ned(gcs: GroundStation, seconds: float) -> tuple[float, float]:
    """(PX4's velocity setpoint, the vehicle's velocity): mean NED vz (m/s) over `seconds`."""
    since = time.monotonic() - seconds
    targets = [msg.vz for t, msg in list(gcs.targets) if t >= since]  # list(): one C-level copy
    samples = gcs.positions_since(since)
    # a handful of each is enough for a mean: under two busy loops PX4 streamed 5 of each in 0.5 s
    assert len(targets) >= 3 and len(samples) >= 3, (len(targets), len(samples))
    return sum(targets) / len(targets), sum(s.vz for s in samples) / len(samples)


def test_px4_flies_the_daemons_climb_and_a_clean_exit_only_warns_of_the_lost_companion(
    shipped: Any, daemon_run: Any, make_policy: Any
) -> None:
    gcs = shipped.gcs
    assert PARAMS["MPC_Z_VEL_MAX_UP"] >= -CLIMB_NED_MPS  # the file lets PX4 fly it
    run = daemon_run(shipped, policy=make_policy(CLIMB_BODY_FLU), engage="auto")
    gcs.wait_until(lambda: gcs.mode is Px4Mode.OFFBOARD, ENGAGE_GUARD_S, "OFFBOARD")
    time.sleep(3.5)  # PX4's acceleration limit (and a low-pass, if the config sets one) settle
    assert gcs.mode is Px4Mode.OFFBOARD
    setpoint_vz, vehicle_vz = mean_vz_ned(gcs, 1.0)
    # Stock-file PX4 clipped its setpoint to -1.00 here; now it flies the command.
    assert abs(setpoint_vz - CLIMB_NED_MPS) <= 0.1, setpoint_vz
    assert vehicle_vz <= 0.85 * CLIMB_NED_MPS, vehicle_vz

    stopped = time.monotonic()
    run.signal(signal.SIGTERM)
    assert run.wait() == 0, run.output()
    gcs.wait_until(lambda: gcs.mode is Px4Mode.HOLD, HEARTBEAT_SLACK_S + 1.0, "HOLD")

    def lost() -> bool:
        return any("mission computer lost" in t for t in gcs.texts_since(stopped))

    gcs.wait_until(lost, OBC_LOSS_T_S + 4.0, "Connection to mission computer lost")
    lost_after_s = time.monotonic() - stopped
    assert lost_after_s >= OBC_LOSS_T_S - 1.0  # the companion's heartbeats ended at the exit
    position = gcs.position()
    assert position is not None
    time.sleep(1.5)  # room for any action PX4 would take on it
    modes = gcs.modes_since(stopped + HEARTBEAT_SLACK_S + 1.0)
    assert modes and all(m.mode is Px4Mode.HOLD and m.armed for m in modes), modes[-3:]
    now = gcs.position()
    assert now is not None and abs(now.z - position.z) < 1.0  # holding its altitude
    texts = gcs.texts_since(stopped)
    assert not [t for t in texts if "Failsafe" in t or "failsafe" in t], texts
