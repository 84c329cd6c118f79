"""firmware_cfg/udev/99-openmv.rules, evaluated for a plugged-in camera by a small interpreter of
the udev rule syntax the file uses (==, !=, GOTO, LABEL, =, +=)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

RULES = Path(__file__).resolve().parents[2] / "firmware_cfg" / "udev" / "99-openmv.rules"
KEY = re.compile(r'\s*([A-Za-z_]+(?:\{[^}]*\})?)\s*(==|!=|\+=|=)\s*"([^"]*)"\s*,?')
PORTS = {"front": "1.1", "right": "1.2", "back": "1.3", "left": "1.4", "up": "1.5", "down": "1.6"}


def parse(text: str) -> list[list[tuple[str, str, str]]]:
    rules = []
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            keys = KEY.findall(line)
            assert "".join(f"{k}{op}{v}" for k, op, v in keys) == re.sub(r'[\s,"]', "", line), (
                f"unparsed text in: {line}"
            )
            rules.append(keys)
    return rules


def apply(rules: list[list[tuple[str, str, str]]], device: dict[str, str]) -> dict[str, str]:
    """The properties a tty device ends with (SYMLINK space-separated)."""
    labels = {v: i for i, rule in enumerate(rules) for k, op, v in rule if k == "LABEL"}
    out: dict[str, str] = {}
    index = 0
    while index < len(rules):
        rule, index = rules[index], index + 1
        matches = [(k, op, v) for k, op, v in rule if op in ("==", "!=")]
        if not all((device.get(k) == v) == (op == "==") for k, op, v in matches):
            continue
        for key, op, value in rule:
            if key == "GOTO":
                index = labels[value]
            elif op == "+=":
                out[key] = f"{out.get(key, '')} {value}".strip()
            elif op == "=" and key != "LABEL":
                out[key] = value
    return out


def camera(vid_pid: str, port: str) -> dict[str, str]:
    vid, pid = vid_pid.split(":")
    return {
        "SUBSYSTEM": "tty",
        "ATTRS{idVendor}": vid,
        "ATTRS{idProduct}": pid,
        "ENV{ID_PATH}": f"platform-xhci-hcd.3.auto-usb-0:{port}:1.0",
    }


@pytest.mark.parametrize("vid_pid", ["1209:abd1", "37c5:1203"])  # firmware < / >= 4.8.1
def test_every_face_gets_its_name_and_the_dialout_group(vid_pid: str) -> None:
    rules = parse(RULES.read_text())
    for face, port in PORTS.items():
        props = apply(rules, camera(vid_pid, port))
        assert props["SYMLINK"] == f"openmv-{face}"
        assert props["GROUP"] == "dialout" and props["MODE"] == "0660"
        assert props["ENV{ID_MM_DEVICE_IGNORE}"] == "1"  # ModemManager keeps away


def test_other_serial_devices_are_left_alone() -> None:
    rules = parse(RULES.read_text())
    assert apply(rules, camera("0403:6001", "1.1")) == {}  # an FTDI adapter on a camera port
    assert apply(rules, camera("37c5:abd1", "1.1")) == {}  # ids of two devices mixed
    assert apply(rules, {**camera("37c5:1203", "1.1"), "SUBSYSTEM": "usb"}) == {}
