"""The daemon's way from a rig image to a velocity command, one tick at a time.

- Each new six-frame image starts an inference on the policy's worker thread, if none is running,
  and the tick waits for it at most `inference_budget_s`; a slower result is taken by a later tick.
- The latest valid policy output is kept with its image: the control law always runs on it, with
  the attitude the drone had when that image was captured (`AttitudeHistory`, sampled at 50 Hz by
  the daemon), so a late output is still rotated into the world correctly.
- A refused output (NaN, out of range: `companion.policy`) is never flown; the reason is reported
  until a valid one comes.

What the command is then used for (fly, hover, fail safe) is the health monitor's decision, not
this module's.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from companion.autopilot_types import AutopilotTelemetry
from companion.camera.rig import RigImage, RigSnapshot
from companion.config import CompanionConfig
from companion.control import ControlLaw, ControlOutput
from companion.geo import MigrationFromHome
from companion.policy import Policy, PolicyOutput
from companion.pose_history import NAN4, AttitudeHistory, FloatArray

Inference = tuple[PolicyOutput, RigImage]  # a finished inference and the image it was run on


class Pilot:
    """Inference scheduling and the control law on the latest valid output."""

    def __init__(self, config: CompanionConfig, event: Callable[[str, str, Any], None]) -> None:
        self._daemon = config.daemon
        self.law = ControlLaw(config.control, nominal_dt_s=config.daemon.period_s)
        self.attitudes = AttitudeHistory()
        self._migration = MigrationFromHome(config.control.migration_point_global, event)
        self._task: asyncio.Task[PolicyOutput] | None = None
        self._task_image: RigImage | None = None
        self._good: Inference | None = None  # latest valid output and its image
        self._last_ok = False
        self._last_reason = "no policy output yet"
        self._last_seqs: tuple[int, ...] | None = None
        self._last_control_s: float | None = None  # the law's filter runs on real tick spacing

    @property
    def output_time_s(self) -> float | None:
        """When the oldest frame of the latest valid output's image arrived; None before one."""
        return None if self._good is None else self._good[1].oldest_receive_time_s

    async def infer(
        self, snapshot: RigSnapshot, policy: Policy
    ) -> tuple[RigImage | None, Inference | None]:
        """Start the inference of `snapshot` if it is a new image and none is running, and wait
        for it at most the tick's budget. Returns (the new image or None, the inference that
        finished since the last call, with its image, or None)."""
        new_image = snapshot if isinstance(snapshot, RigImage) else None
        if new_image is not None and new_image.seqs == self._last_seqs:
            new_image = None
        if new_image is not None:
            self._last_seqs = new_image.seqs
            if self._task is None:
                self._task_image = new_image
                self._task = asyncio.create_task(policy.infer(new_image.image))
                await asyncio.wait({self._task}, timeout=self._daemon.budget_s)
        return new_image, self._collect()

    def _collect(self) -> Inference | None:
        """Take a finished inference's result and its image; None if none finished."""
        task, image = self._task, self._task_image
        if task is None or not task.done() or image is None:
            return None
        self._task = self._task_image = None
        output = task.result()
        if output.ok:
            self._good = (output, image)
            self._last_ok, self._last_reason = True, ""
        else:
            self._last_ok, self._last_reason = False, f"policy output refused: {output.reason}"
        return output, image

    def control(
        self,
        now_s: float,
        snapshot: RigSnapshot,
        telemetry: AutopilotTelemetry,
        pos_enu: FloatArray,
        yaw_enu: float,
        policy: Policy,
    ) -> tuple[ControlOutput | None, bool, str]:
        """The control law on the latest valid output: (output or None, valid, why not)."""
        if not self._last_ok or self._good is None:
            return None, False, self._last_reason
        migration, waiting = self._migration.resolve(telemetry.home)
        if waiting:
            return None, False, waiting
        output, image = self._good
        max_age_s = self._daemon.telemetry_max_age_s
        q_capture = self.attitudes.at(image.oldest_capture_time_s, max_age_s)
        dt_s = None if self._last_control_s is None else now_s - self._last_control_s
        self._last_control_s = now_s
        home = telemetry.home  # the EKF origin until PX4 reports one
        control = self.law.step(
            output.vel_body_flu,
            NAN4 if q_capture is None else q_capture,
            pos_enu,
            yaw_enu,
            dt_s=dt_s if dt_s is not None and dt_s > 0.0 else None,
            migration_point_world_enu=migration,
            home_z_enu_m=0.0 if home is None else home.value.z_enu_m,  # the band's zero
        )
        if not control.ok:
            return control, False, control.reason
        return control, True, _stale_problem(snapshot, policy, now_s)

    def cancel(self) -> None:
        """Stop waiting for a running inference (the model thread itself is the policy's)."""
        if self._task is not None:
            self._task.cancel()


def _stale_problem(snapshot: RigSnapshot, policy: Policy, now_s: float) -> str:
    """Why no fresh output may be coming (shown only if the output turns out stale)."""
    if not isinstance(snapshot, RigImage):
        return f"no fresh rig image: {snapshot.reason}"
    since = policy.in_flight_since
    if since is not None:
        return f"no fresh inference: the model has been running for {now_s - since:.3f} s"
    return ""
