"""Camera rig config: TOML round trip, defaults, and errors that name the field and the range."""

from __future__ import annotations

import dataclasses
import tomllib
from typing import Any

import pytest

from companion.camera.config import CameraRigConfig, FaceCameraConfig
from companion.camera.layout import FACE_NAMES
from companion.camera.serial_link import SerialCameraLink
from companion.errors import ConfigError

UIDS = {face: f"3A0025000D51363036383{index:03X}" for index, face in enumerate(FACE_NAMES)}
TOML = "\n".join(
    ["[cameras]", "baud = 115200", "max_age_s = 0.25"]
    + [
        f'[cameras.faces.{face}]\ndevice = "/dev/openmv-{face}"\ncamera_id = "{UIDS[face]}"'
        for face in FACE_NAMES
    ]
)


def table(**changes: Any) -> dict[str, Any]:
    d: dict[str, Any] = tomllib.loads(TOML)["cameras"]
    d.update(changes)
    return d


def test_from_toml_with_defaults_and_normalized_ids() -> None:
    config = CameraRigConfig.from_dict(table())
    assert config.max_age_s == 0.25
    assert (config.baud, config.max_skew_s) == (115200, 0.15)
    assert (config.reconnect_min_s, config.reconnect_max_s, config.silence_timeout_s) == (
        0.1,
        2.0,
        2.0,
    )
    assert tuple(config.faces) == FACE_NAMES
    assert config.faces["up"].device == "/dev/openmv-up"
    assert config.faces["up"].camera_id == UIDS["up"].lower()
    assert config.face_of_camera(UIDS["left"]) == "left"
    assert config.face_of_camera("abcd") is None
    assert CameraRigConfig.from_dict(config.to_dict()) == config
    assert dataclasses.asdict(config)["faces"]["up"]["device"] == "/dev/openmv-up"


@pytest.mark.parametrize("baud", [921600, 12000000])
def test_openmv_debug_bauds_are_refused(baud: int) -> None:
    with pytest.raises(ConfigError, match=rf"cameras\.baud: {baud} is reserved .*IDE debug"):
        CameraRigConfig.from_dict(table(baud=baud))
    with pytest.raises(ConfigError, match="baud"):
        SerialCameraLink("/dev/null", baud=baud)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"baud": 115200.0}, r"cameras\.baud: expected an integer"),
        ({"baud": 300}, r"cameras\.baud: 300 is outside the allowed range \[1200, 4000000\]"),
        ({"max_age_s": 0}, r"cameras\.max_age_s: 0 is outside the allowed range \(0, 10\]"),
        ({"max_skew_s": -0.1}, r"cameras\.max_skew_s: .*range \(0, 10\]"),
        ({"reconnect_min_s": 0.0}, r"cameras\.reconnect_min_s: .*range \(0, 60\]"),
        ({"reconnect_max_s": 0.05}, r"cameras\.reconnect_max_s: 0\.05 .*range \[0\.1, 60\]"),
        ({"silence_timeout_s": float("nan")}, r"cameras\.silence_timeout_s: must be finite"),
        ({"max_age_s": "0.3"}, r"cameras\.max_age_s: expected a number of seconds, got '0\.3'"),
        ({"baudrate": 115200}, r"cameras: unknown key\(s\) 'baudrate'; allowed keys: faces, baud"),
    ],
)
def test_bad_values_name_the_field_and_range(changes: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        CameraRigConfig.from_dict(table(**changes))


def test_face_table_errors_name_the_face() -> None:
    d = table()
    d["faces"]["top"] = d["faces"].pop("up")
    with pytest.raises(ConfigError, match=r"cameras\.faces: unknown key\(s\) 'top'"):
        CameraRigConfig.from_dict(d)
    d = table()
    del d["faces"]["down"]
    with pytest.raises(ConfigError, match=r"cameras\.faces: missing face\(s\) down"):
        CameraRigConfig.from_dict(d)
    d = table()
    d["faces"]["left"]["camera_id"] = "xyz"
    with pytest.raises(ConfigError, match=r"cameras\.faces\.left\.camera_id: 'xyz' is not"):
        CameraRigConfig.from_dict(d)
    d = table()
    del d["faces"]["back"]["device"]
    with pytest.raises(ConfigError, match=r"cameras\.faces\.back\.device: missing"):
        CameraRigConfig.from_dict(d)
    d = table()
    d["faces"]["back"]["port"] = "/dev/ttyACM0"
    with pytest.raises(ConfigError, match=r"cameras\.faces\.back: unknown key\(s\) 'port'"):
        CameraRigConfig.from_dict(d)
    with pytest.raises(ConfigError, match=r"cameras\.faces: missing"):
        CameraRigConfig.from_dict({"baud": 115200})


def test_each_camera_and_device_serves_one_face() -> None:
    d = table()
    d["faces"]["back"]["camera_id"] = UIDS["front"].lower()
    with pytest.raises(ConfigError, match=r"back\.camera_id: .* already used by face 'front'"):
        CameraRigConfig.from_dict(d)
    d = table()
    d["faces"]["down"]["device"] = "/dev/openmv-up"
    with pytest.raises(ConfigError, match=r"faces\.down\.device: .* already used by face 'up'"):
        CameraRigConfig.from_dict(d)


def test_direct_construction_is_validated_too() -> None:
    with pytest.raises(ConfigError, match=r"FaceCameraConfig\.device"):
        FaceCameraConfig(device="", camera_id="00")
    faces = {f: FaceCameraConfig(f"/dev/{f}", UIDS[f]) for f in FACE_NAMES}
    with pytest.raises(ConfigError, match=r"cameras\.max_age_s"):
        CameraRigConfig(faces=faces, max_age_s=-1.0)
