"""Configuration of the camera rig: which serial device and which camera serve each cube face.

TOML shape (the `[cameras]` section of the companion config; every key but `faces` optional):

```toml
[cameras]
baud = 115200            # never 921600 or 12000000: OpenMV firmware treats those as IDE debug mode
max_age_s = 0.3          # a face whose latest frame was received longer ago is stale
max_skew_s = 0.15        # largest spread of receive times across the six faces
reconnect_min_s = 0.1    # first reconnect delay after an unplug; doubles up to reconnect_max_s
reconnect_max_s = 2.0
silence_timeout_s = 2.0  # an open port silent this long is closed and reopened

[cameras.faces.front]
device = "/dev/openmv-front"           # stable udev name (firmware_cfg/udev)
camera_id = "3a0025000d51363036383832" # board unique id from the camera's HELLO (lowercase hex)
# ... one table per face: front, right, back, left, up, down
```

Cameras are identified in-band (HELLO `uid`), never by USB serial number: several OpenMV firmware
builds report the same serial number for every camera.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.camera.layout import FACE_NAMES
from companion.errors import ConfigError, problems_error
from companion.sections import build_collecting
from companion.validation import require_int_range, require_range

SECTION = "cameras"
DEFAULT_BAUD = 115200
# The OpenMV firmware switches to its IDE debug protocol when the port is opened at these rates.
FORBIDDEN_BAUDS: frozenset[int] = frozenset({921600, 12000000})
BAUD_MIN = 1200
BAUD_MAX = 4_000_000
_HEX_DIGITS = frozenset("0123456789abcdef")


def normalize_camera_id(field_name: str, value: object) -> str:
    """Lowercase hex board id, 2..64 digits (even count), as HELLO carries it; else ConfigError."""
    if not isinstance(value, str):
        raise ConfigError(f"{field_name}: expected a hex string, got {value!r}")
    text = value.strip().lower()
    if not (2 <= len(text) <= 64 and len(text) % 2 == 0 and set(text) <= _HEX_DIGITS):
        raise ConfigError(
            f"{field_name}: {value!r} is not a board unique id (2..64 hex digits, even count)"
        )
    return text


def validate_baud(field_name: str, value: int) -> int:
    """Baud rate in [BAUD_MIN, BAUD_MAX], never one of `FORBIDDEN_BAUDS`."""
    baud = require_int_range(field_name, value, 0)
    if baud in FORBIDDEN_BAUDS:
        raise ConfigError(
            f"{field_name}: {baud} is reserved by the OpenMV firmware for IDE debug mode; "
            f"use another rate in [{BAUD_MIN}, {BAUD_MAX}] except 921600, e.g. {DEFAULT_BAUD}"
        )
    return require_int_range(field_name, baud, BAUD_MIN, BAUD_MAX)


def _check_keys(where: str, table: Mapping[str, Any], allowed: tuple[str, ...]) -> None:
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}; "
            f"allowed keys: {', '.join(allowed)}"
        )


def _require_table(where: str, value: object) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a table, got {type(value).__name__}")
    return value


def _check_device(field_name: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{field_name}: expected a non-empty device path, got {value!r}")
    return value


@dataclass(frozen=True)
class FaceCameraConfig:
    """One face: the serial device to read and the camera (board unique id) expected on it."""

    device: str  # e.g. "/dev/openmv-front" (a stable udev symlink)
    camera_id: str  # HELLO uid, lowercase hex; normalized on construction

    def __post_init__(self) -> None:
        _check_device("FaceCameraConfig.device", self.device)
        camera_id = normalize_camera_id("FaceCameraConfig.camera_id", self.camera_id)
        object.__setattr__(self, "camera_id", camera_id)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, where: str) -> FaceCameraConfig:
        """From a TOML table with exactly `device` and `camera_id`; errors name `where.key`."""
        table = _require_table(where, d)
        _check_keys(where, table, ("device", "camera_id"))
        for key in ("device", "camera_id"):
            if key not in table:
                raise ConfigError(f"{where}.{key}: missing (required)")
        return cls(
            device=_check_device(f"{where}.device", table["device"]),
            camera_id=normalize_camera_id(f"{where}.camera_id", table["camera_id"]),
        )


@dataclass(frozen=True)
class CameraRigConfig:
    """The six cameras and the rig's freshness rules. Times in seconds (host monotonic clock)."""

    faces: Mapping[str, FaceCameraConfig]  # exactly the six FACE_NAMES, stored in that order
    baud: int = DEFAULT_BAUD
    max_age_s: float = 0.3
    max_skew_s: float = 0.15
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 2.0
    silence_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        s = SECTION
        faces = _require_table(f"{s}.faces", self.faces)
        unknown = sorted(set(faces) - set(FACE_NAMES))
        if unknown:
            raise ConfigError(
                f"{s}.faces: unknown face(s) {', '.join(repr(k) for k in unknown)}; "
                f"allowed: {', '.join(FACE_NAMES)}"
            )
        missing = [name for name in FACE_NAMES if name not in faces]
        if missing:
            raise ConfigError(f"{s}.faces: missing face(s) {', '.join(missing)}; all six needed")
        ordered: dict[str, FaceCameraConfig] = {}
        for name in FACE_NAMES:
            face = faces[name]
            if not isinstance(face, FaceCameraConfig):
                raise ConfigError(f"{s}.faces.{name}: expected a FaceCameraConfig")
            ordered[name] = face
        self._check_unique(ordered)
        object.__setattr__(self, "faces", ordered)  # a plain dict: dataclasses.asdict works
        validate_baud(f"{s}.baud", self.baud)
        limits = {"max_age_s": (0.0, 10.0), "max_skew_s": (0.0, 10.0),
                  "reconnect_min_s": (0.0, 60.0), "reconnect_max_s": (None, 60.0),
                  "silence_timeout_s": (0.0, 60.0)}  # fmt: skip
        for key, (low, high) in limits.items():
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(f"{s}.{key}: expected a number of seconds, got {value!r}")
            if low is None:  # reconnect_max_s: at least reconnect_min_s
                seconds = require_range(f"{s}.{key}", value, self.reconnect_min_s, high)
            else:
                seconds = require_range(f"{s}.{key}", value, low, high, low_inclusive=False)
            object.__setattr__(self, key, seconds)

    @staticmethod
    def _check_unique(faces: Mapping[str, FaceCameraConfig]) -> None:
        for attr in ("device", "camera_id"):
            seen: dict[str, str] = {}
            for name, face in faces.items():
                value = getattr(face, attr)
                if value in seen:
                    raise ConfigError(
                        f"{SECTION}.faces.{name}.{attr}: {value!r} is already used by face "
                        f"{seen[value]!r}; each face needs its own"
                    )
                seen[value] = name

    def face_of_camera(self, camera_id: str) -> str | None:
        """The face configured for a board unique id (lowercase hex), or None if not in the map."""
        wanted = camera_id.lower()
        return next((name for name, f in self.faces.items() if f.camera_id == wanted), None)

    def to_dict(self) -> dict[str, Any]:
        """The `[cameras]` TOML table (inverse of `from_dict`)."""
        out: dict[str, Any] = {
            "faces": {name: {"device": f.device, "camera_id": f.camera_id}
                      for name, f in self.faces.items()},
        }  # fmt: skip
        for key in ("baud", "max_age_s", "max_skew_s", "reconnect_min_s", "reconnect_max_s",
                    "silence_timeout_s"):  # fmt: skip
            out[key] = getattr(self, key)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CameraRigConfig:
        """From the parsed `[cameras]` TOML table; unknown keys are refused, naming them."""
        table = _require_table(SECTION, d)
        allowed = ("faces", "baud", "max_age_s", "max_skew_s", "reconnect_min_s",
                   "reconnect_max_s", "silence_timeout_s")  # fmt: skip
        problems: list[str] = []  # every problem of the section, reported at once
        try:
            _check_keys(SECTION, table, allowed)
        except ConfigError as exc:
            problems.append(str(exc))
        options = {key: table[key] for key in allowed[1:] if key in table}
        if "faces" not in table:
            problems.append(f"{SECTION}.faces: missing (one table per face: "
                            f"{', '.join(FACE_NAMES)})")  # fmt: skip
            build_collecting(cls, SECTION, {"faces": _placeholder_faces(), **options}, problems)
            raise problems_error(problems)
        faces_table = _require_table(f"{SECTION}.faces", table["faces"])
        try:
            _check_keys(f"{SECTION}.faces", faces_table, FACE_NAMES)
        except ConfigError as exc:
            problems.append(str(exc))
        faces: dict[str, FaceCameraConfig] = {}
        for name, value in faces_table.items():
            if name not in FACE_NAMES:
                continue
            try:
                faces[name] = FaceCameraConfig.from_dict(value, where=f"{SECTION}.faces.{name}")
            except ConfigError as exc:
                problems.append(str(exc))
        complete = len(faces) == len(faces_table) and not problems
        # With a face refused, check the other options against stand-in faces.
        kwargs = {"faces": faces if complete else _placeholder_faces(), **options}
        built = build_collecting(cls, SECTION, kwargs, problems)
        if built is None or problems:
            raise problems_error(problems)
        return built


def _placeholder_faces() -> dict[str, FaceCameraConfig]:
    """Six valid faces, to check a `[cameras]` table's other options when its faces are bad."""
    return {
        name: FaceCameraConfig(device=f"/dev/placeholder-{name}", camera_id=f"{k + 1:024x}")
        for k, name in enumerate(FACE_NAMES)
    }
