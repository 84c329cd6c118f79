"""The companion's one TOML file: every section's dataclass, composed and validated on load.

```toml
[drone]        # id = "drone3"  (names the logs and the telemetry keys swarm/<id>/...)
[cameras]      # companion.camera.config.CameraRigConfig: six faces (device, camera_id), freshness
[policy]       # companion.policy.PolicyConfig: model_path (relative: to this file), sha256
[control]      # companion.control.ControlConfig: migration point, speed cap, altitude band
[autopilot]    # companion.autopilot_types.AutopilotConfig: MAVSDK url, timeouts, failsafe action
[recorder]     # companion.recorder.RecorderConfig: directory (relative: to this file), rotation
[telemetry]    # companion.telemetry.TelemetryConfig: Zenoh endpoints (loopback by default)
[daemon]       # DaemonConfig below: loop rate, hover and failsafe delays, engagement, watchdog
```

`[cameras]` and `[policy]` are required (faces and model path have no sensible default); every
other section and key is optional and defaults to the paper's values. Unknown sections and keys
are refused, naming them; every error names `section.field` and the allowed range, and every
problem of the file is reported at once (`ConfigErrors`), so it is fixed in one pass.

Cross-section rules: `[drone].id` is the telemetry drone id (`[telemetry].drone_id`, if given,
must agree); the daemon sends one setpoint per tick, so `[autopilot].setpoint_rate_hz`, if given,
must equal `[daemon].rate_hz` (otherwise it is set to it).
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

from companion.autopilot_types import AutopilotConfig
from companion.camera.config import CameraRigConfig
from companion.control import ControlConfig
from companion.errors import ConfigError, problems_error, problems_of
from companion.policy import PolicyConfig
from companion.recorder import RecorderConfig
from companion.sections import check_keys, require_bool, require_table, section_from_dict
from companion.telemetry import TelemetryConfig
from companion.validation import require_range

SECTIONS = ("drone", "cameras", "policy", "control", "autopilot", "recorder", "telemetry", "daemon")
REQUIRED_SECTIONS = ("cameras", "policy")
ENGAGE_MODES = ("operator", "ground", "auto", "never")
UNIX_PATH_MAX = 107  # bytes of a unix socket path (sun_path is 108 with its NUL)
LOG_LEVELS = ("debug", "info", "warning", "error")
_ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
T = TypeVar("T")


@dataclass(frozen=True)
class DroneConfig:
    """The `[drone]` section."""

    id: str = "drone0"  # 1-64 of A-Z a-z 0-9 _ -; log file names and telemetry keys

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not _ID_RE.match(self.id):
            raise ConfigError(f"drone.id: {self.id!r} must be 1-64 of A-Z a-z 0-9 _ -")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DroneConfig:
        return section_from_dict(cls, "drone", data)


@dataclass(frozen=True)
class DaemonConfig:
    """The `[daemon]` section. Times in seconds of the monotonic clock.

    - `rate_hz`: control loop rate; one setpoint per tick (PX4 needs > 2 Hz, cameras run at 10).
    - `tick_on_frames`: a tick starts as soon as all six cameras delivered a new frame, so each
      decision acts on the newest image; `rate_hz` stays the floor (a tick at the latest one
      period after the previous). False: ticks on the fixed `rate_hz` grid only.
    - `stale_hover_after_s`: the command's source image (its oldest tile) older than this, or no
      valid policy output: hover (zero velocity, yaw held).
    - `failsafe_after_s`: hovering longer than this: the autopilot's failsafe
      (`[autopilot].failsafe_action`, Hold or Land), then the daemon stops commanding.
    - `inference_budget_s`: how long a tick waits for the inference of the image it just took;
      a slower model's result is used by a later tick (shorter than the period; None: half).
    - `engage`: who engages OFFBOARD. "operator" (the default): once the pipeline is healthy the
      daemon streams hover setpoints and the pilot or the ground station switches the vehicle to
      OFFBOARD; "ground": the daemon requests OFFBOARD itself, but only after `companion engage`
      on the control socket (the ground station runs it over SSH); "auto": the daemon requests
      OFFBOARD as soon as it is healthy (simulation harnesses only: no operator action at all);
      "never": runs everything but never commands (bench tests). Every mode waits, if
      `engage_requires_airborne`, for the vehicle armed and in the air (on the ground the
      altitude floor would make it climb), and never engages during a PX4 failsafe or without
      the autopilot's heartbeat.
    - `control_socket`: the local control channel (`companion engage|disengage|status`), a unix
      socket only root and the service user can reach (mode 0660 in a 0750 directory); "" : none.
    - `engage_retry_s`: wait after a refused OFFBOARD request before trying again.
    - `telemetry_max_age_s`: attitude and position older than this are not used (hover).
    - `watchdog_max_late_s`: a tick starting later than this after its deadline withholds the
      systemd WATCHDOG=1 ping (the loop is not healthy).
    - `shutdown_timeout_s`: bound on each shutdown step (zero setpoint + Hold, closing outputs).
    """

    rate_hz: float = 10.0
    tick_on_frames: bool = True
    stale_hover_after_s: float = 0.3
    failsafe_after_s: float = 3.0
    inference_budget_s: float | None = None
    engage: str = "operator"
    control_socket: str = "/run/vision-swarm/control.sock"
    engage_requires_airborne: bool = True
    engage_retry_s: float = 2.0
    telemetry_max_age_s: float = 0.5
    watchdog_max_late_s: float = 0.5
    shutdown_timeout_s: float = 5.0
    log_level: str = "info"

    def __post_init__(self) -> None:
        s = "daemon"
        require_range(f"{s}.rate_hz", self.rate_hz, 10.0, 100.0)
        require_bool(f"{s}.tick_on_frames", self.tick_on_frames)
        require_range(
            f"{s}.stale_hover_after_s", self.stale_hover_after_s, 0.0, 10.0, low_inclusive=False
        )
        require_range(
            f"{s}.failsafe_after_s", self.failsafe_after_s, 0.0, 600.0, low_inclusive=False
        )
        if self.inference_budget_s is not None:
            require_range(
                f"{s}.inference_budget_s",
                self.inference_budget_s,
                0.0,
                1.0 / self.rate_hz,
                high_inclusive=False,
            )
        if self.engage not in ENGAGE_MODES:
            raise ConfigError(
                f"{s}.engage: {self.engage!r} must be one of {', '.join(ENGAGE_MODES)}"
            )
        if not isinstance(self.control_socket, str) or (
            self.control_socket
            and (
                not self.control_socket.startswith("/")
                or len(self.control_socket.encode()) > UNIX_PATH_MAX
            )
        ):
            raise ConfigError(
                f"{s}.control_socket: {self.control_socket!r} must be an absolute path of at most "
                f'{UNIX_PATH_MAX} bytes, or "" for none'
            )
        require_bool(f"{s}.engage_requires_airborne", self.engage_requires_airborne)
        require_range(f"{s}.engage_retry_s", self.engage_retry_s, 0.0, 600.0)
        require_range(
            f"{s}.telemetry_max_age_s", self.telemetry_max_age_s, 0.0, 10.0, low_inclusive=False
        )
        require_range(
            f"{s}.watchdog_max_late_s", self.watchdog_max_late_s, 0.0, 60.0, low_inclusive=False
        )
        require_range(
            f"{s}.shutdown_timeout_s", self.shutdown_timeout_s, 0.0, 60.0, low_inclusive=False
        )
        if self.log_level not in LOG_LEVELS:
            raise ConfigError(f"{s}.log_level: {self.log_level!r} must be one of {LOG_LEVELS}")

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def budget_s(self) -> float:
        """The inference wait per tick: `inference_budget_s`, or half the period."""
        budget = self.inference_budget_s
        return self.period_s / 2.0 if budget is None else budget

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DaemonConfig:
        return section_from_dict(cls, "daemon", data)


@dataclass(frozen=True)
class CompanionConfig:
    """The whole file, one validated dataclass per section; `source`: the file it came from."""

    cameras: CameraRigConfig
    policy: PolicyConfig
    drone: DroneConfig = field(default_factory=DroneConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    source: Path | None = None


def config_from_dict(data: Mapping[str, Any], base_dir: Path | None = None) -> CompanionConfig:
    """Build and validate the config from a parsed TOML document.

    Relative paths (`policy.model_path`, `recorder.directory`) are taken from `base_dir`. Every
    section is checked, and every problem found is raised at once (`ConfigErrors` when several).
    """
    document = require_table("config", data)
    problems: list[str] = []
    try:
        check_keys("config", document, SECTIONS)
    except ConfigError as exc:
        problems.append(str(exc))
    for name in REQUIRED_SECTIONS:
        if name not in document:
            problems.append(f"{name}: missing section [{name}] (required)")

    def build(name: str, make: Callable[[Mapping[str, Any]], T]) -> T | None:
        if name in REQUIRED_SECTIONS and name not in document:
            return None
        try:
            return make(require_table(name, document.get(name, {})))
        except ConfigError as exc:
            problems.extend(problems_of(exc))
            return None

    drone = build("drone", DroneConfig.from_dict)
    daemon = build("daemon", DaemonConfig.from_dict)
    cameras = build("cameras", CameraRigConfig.from_dict)
    policy = build("policy", lambda t: PolicyConfig.from_dict(t, base_dir=base_dir))
    control = build("control", ControlConfig.from_dict)
    recorder = build("recorder", lambda t: RecorderConfig.from_dict(t, base_dir=base_dir))

    def autopilot_from(table: Mapping[str, Any]) -> AutopilotConfig:
        table = dict(table)
        if daemon is None:  # its rate is reported already; check the rest against the default
            table.pop("setpoint_rate_hz", None)
            return AutopilotConfig.from_dict(table)
        rate = table.setdefault("setpoint_rate_hz", daemon.rate_hz)
        if rate != daemon.rate_hz:
            problems.append(
                f"autopilot.setpoint_rate_hz: {rate!r} differs from daemon.rate_hz "
                f"({daemon.rate_hz:g}); the daemon sends one setpoint per tick: set only "
                "daemon.rate_hz"
            )
            table["setpoint_rate_hz"] = daemon.rate_hz
        return AutopilotConfig.from_dict(table)

    def telemetry_from(table: Mapping[str, Any]) -> TelemetryConfig:
        table = dict(table)
        if drone is None:  # its id is reported already
            table.pop("drone_id", None)
            return TelemetryConfig.from_dict(table)
        given_id = table.setdefault("drone_id", drone.id)
        if given_id != drone.id:
            problems.append(
                f"telemetry.drone_id: {given_id!r} differs from drone.id ({drone.id!r}); "
                "set only drone.id"
            )
            table["drone_id"] = drone.id
        return TelemetryConfig.from_dict(table)

    autopilot = build("autopilot", autopilot_from)
    telemetry = build("telemetry", telemetry_from)
    if problems:
        raise problems_error(problems)
    assert drone and daemon and cameras and policy and control and recorder
    assert autopilot and telemetry
    return CompanionConfig(
        drone=drone,
        cameras=cameras,
        policy=policy,
        control=control,
        autopilot=autopilot,
        recorder=recorder,
        telemetry=telemetry,
        daemon=daemon,
    )


def load_config(path: str | Path) -> CompanionConfig:
    """Read, parse and validate a TOML config file (raises `ConfigError` naming the problem)."""
    source = Path(path).expanduser()
    try:
        text = source.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config file {source}: {exc.strerror or exc}") from exc
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from exc
    try:
        config = config_from_dict(document, base_dir=source.resolve().parent)
    except ConfigError as exc:
        raise problems_error(problems_of(exc), where=str(source)) from exc
    return replace(config, source=source)
