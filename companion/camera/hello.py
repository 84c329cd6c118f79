"""HELLO payload of camera protocol v1: build it (encoder side) and check it (parser side).

The rules (docs/camera-protocol.md, "HELLO payload"), the same for both directions:

- the payload is ASCII bytes (every byte < 0x80) holding one JSON object;
- `uid`: the board unique id, lowercase hex, an even number of digits, 2..64 (1..32 bytes);
- `fw` and the optional `omv`: printable ASCII (0x20..0x7E), at most 64 characters;
- `proto`: an integer equal to the protocol version of the header it came in (1 in v1).

A HELLO that breaks any rule is not a HELLO: the parser counts it in `invalid_messages`.
Imports only the standard library.
"""

from __future__ import annotations

import json
from typing import NamedTuple

UID_MAX_DIGITS = 64
TEXT_MAX_CHARS = 64
_HEX_LOWER = frozenset("0123456789abcdef")


class HelloBody(NamedTuple):
    """The checked content of a HELLO payload."""

    unique_id: str
    firmware: str
    protocol_version: int
    platform: str


def is_uid(text: object) -> bool:
    """Whether `text` is a board unique id as the wire carries it: lowercase hex, 2..64 digits,
    an even count."""
    return (
        isinstance(text, str)
        and 0 < len(text) <= UID_MAX_DIGITS
        and len(text) % 2 == 0
        and set(text) <= _HEX_LOWER
    )


def is_text(text: object) -> bool:
    """Whether `text` may be a HELLO `fw` / `omv` value: printable ASCII, at most 64 chars."""
    return (
        isinstance(text, str)
        and len(text) <= TEXT_MAX_CHARS
        and all(" " <= ch <= "~" for ch in text)
    )


def build_hello_payload(uid: str, firmware: str, platform: str, version: int) -> bytes | None:
    """Compact JSON {"uid","fw","proto","omv"} in that key order, no spaces (as the firmware
    writes it); None if a value breaks a rule (the caller raises its own error)."""
    if not (is_uid(uid) and is_text(firmware) and is_text(platform)):
        return None
    body = {"uid": uid, "fw": firmware, "proto": version, "omv": platform}
    return json.dumps(body, separators=(",", ":")).encode("ascii")


def parse_hello_payload(payload: bytes, version: int) -> HelloBody | None:
    """The checked HELLO content of a payload that came in a header of `version`; None if the
    payload breaks a rule (not ASCII, not a JSON object, a key missing or out of range)."""
    if not payload.isascii():
        return None
    try:
        body = json.loads(payload)
        uid, firmware, proto = body["uid"], body["fw"], body["proto"]
        platform = body.get("omv", "")
    except (ValueError, TypeError, KeyError, AttributeError):
        return None
    proto_ok = isinstance(proto, int) and not isinstance(proto, bool) and proto == version
    if not (proto_ok and is_uid(uid) and is_text(firmware) and is_text(platform)):
        return None
    return HelloBody(uid, firmware, proto, platform)
