"""What the PX4 emulator (`sim_harness.hil.autopilot_emulator`) is told before it starts: the
client's UDP port, its MAVLink ids, the stream and physics rates, the vehicle's start state and
PX4's own rules (`px4_logic.Px4LogicConfig`). Also `free_udp_port`: two listeners on one UDP port
do not fail on Linux, so every emulator of a harness gets a port nothing is bound to.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass, field
from typing import Any

from companion.validation import require_int_range, require_non_negative, require_positive
from sim_harness.errors import ConfigError
from sim_harness.hil import px4_messages as msgs
from sim_harness.hil.px4_logic import Px4LogicConfig, Px4Mode

LOOPBACK = "127.0.0.1"


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((LOOPBACK, 0))
        return int(sock.getsockname()[1])


@dataclass(frozen=True)
class EmulatorConfig:
    """Where to send, how often, and how the vehicle starts.

    `client_port`: the UDP port the client listens on (MAVSDK `udpin://127.0.0.1:PORT`).
    Rates in Hz; the start state is on the ground, disarmed, in `start_mode`, unless
    `start_altitude_m` > 0 (then `start_armed` must be True: hovering at that altitude).
    """

    client_port: int
    system_id: int = 1
    component_id: int = 1
    heartbeat_rate_hz: float = 1.0
    telemetry_rate_hz: float = 30.0  # LOCAL_POSITION_NED, ATTITUDE(_QUATERNION), GLOBAL_POSITION
    status_rate_hz: float = 2.0  # SYS_STATUS (battery), EXTENDED_SYS_STATE, HOME_POSITION, GPS
    physics_rate_hz: float = 50.0
    start_mode: Px4Mode = Px4Mode.HOLD
    start_armed: bool = False
    start_altitude_m: float = 0.0
    start_yaw_rad: float = 0.0
    home: msgs.Home = field(default_factory=lambda: msgs.Home(47.397742, 8.545594, 488.0))
    log_capacity: int = 10_000  # setpoints and commands kept (oldest dropped first)
    px4: Px4LogicConfig = field(default_factory=Px4LogicConfig)

    def __post_init__(self) -> None:
        require_int_range("emulator.client_port", self.client_port, 1, 65535)
        require_int_range("emulator.system_id", self.system_id, 1, 255)
        require_int_range("emulator.component_id", self.component_id, 1, 255)
        for name in ("heartbeat_rate_hz", "telemetry_rate_hz", "status_rate_hz"):
            require_positive(f"emulator.{name}", getattr(self, name))
        require_positive("emulator.physics_rate_hz", self.physics_rate_hz)
        require_non_negative("emulator.start_altitude_m", self.start_altitude_m)
        require_int_range("emulator.log_capacity", self.log_capacity, 1)
        if self.start_altitude_m > 0.0 and not self.start_armed:
            raise ConfigError("emulator.start_armed: must be True when start_altitude_m > 0")

    @classmethod
    def hovering(cls, client_port: int, altitude_m: float = 5.0, **kwargs: Any) -> EmulatorConfig:
        """Armed and hovering at `altitude_m` in POSCTL, as if a pilot had taken off."""
        kwargs.setdefault("start_mode", Px4Mode.POSCTL)
        return cls(client_port, start_armed=True, start_altitude_m=altitude_m, **kwargs)
