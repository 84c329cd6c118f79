"""Camera rig: freshness, skew and camera-id rules; stitching order (pure logic, injected times)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.camera.config import CameraRigConfig, FaceCameraConfig
from companion.camera.layout import FACE_NAMES, FACE_SIZE_PX, stitch
from companion.camera.rig import FaceProblem, Rig, RigImage, RigNotReady
from companion.camera.slot import CameraFrame, CaptureClock, LatestSlot
from companion.errors import ConfigError

UIDS = {face: f"{index + 1:02x}" * 12 for index, face in enumerate(FACE_NAMES)}
NOW_S = 100.0


def make_config(**options: float) -> CameraRigConfig:
    faces = {f: FaceCameraConfig(device=f"/dev/openmv-{f}", camera_id=UIDS[f]) for f in FACE_NAMES}
    return CameraRigConfig(faces=faces, **options)


def tile(face: str) -> np.ndarray:
    seed = FACE_NAMES.index(face)
    return np.random.default_rng(seed).integers(0, 256, (FACE_SIZE_PX, FACE_SIZE_PX), np.uint8)


def frame(
    face: str, receive_s: float = NOW_S, uid: str | None = "", capture_s: float | None = None
) -> CameraFrame:
    return CameraFrame(
        image=tile(face),
        seq=FACE_NAMES.index(face) + 10,
        capture_timestamp_us=1_000,
        capture_time_s=receive_s - 0.01 if capture_s is None else capture_s,
        receive_time_s=receive_s,
        camera_uid=UIDS[face] if uid == "" else uid,
        header_camera_id=FACE_NAMES.index(face),
        device=f"/dev/openmv-{face}",
    )


@pytest.fixture
def slots() -> dict[str, LatestSlot]:
    out = {face: LatestSlot() for face in FACE_NAMES}
    for face, slot in out.items():
        slot.publish(frame(face))
    return out


def not_ready(result: object) -> RigNotReady:
    assert isinstance(result, RigNotReady), result
    assert not result.ready
    return result


def test_fresh_faces_stitch_in_face_names_order(slots: dict[str, LatestSlot]) -> None:
    slots["left"].publish(frame("left", NOW_S - 0.05, capture_s=NOW_S - 0.09))
    result = Rig(make_config(), slots).snapshot(NOW_S)
    assert isinstance(result, RigImage) and result.ready
    assert result.image.shape == (64, 384) and result.image.dtype == np.uint8
    assert np.array_equal(result.image, stitch([tile(face) for face in FACE_NAMES]))
    assert np.array_equal(result.image[:, 128:192], tile("back"))  # third tile from the left
    assert result.receive_times_s[FACE_NAMES.index("left")] == NOW_S - 0.05
    assert result.oldest_receive_time_s == NOW_S - 0.05
    assert result.oldest_capture_time_s == NOW_S - 0.09
    assert result.seqs == tuple(range(10, 16))
    assert result.camera_uids == tuple(UIDS[face] for face in FACE_NAMES)


def test_stale_face_is_named_and_nothing_is_stitched(slots: dict[str, LatestSlot]) -> None:
    slots["up"].publish(frame("up", NOW_S - 0.31))
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.faces == ("up",)
    assert result.problems("up") == (FaceProblem.STALE,)
    assert result.reason.startswith("up: stale (age 0.310 s > 0.300 s")


def test_age_limit_is_inclusive_and_configurable(slots: dict[str, LatestSlot]) -> None:
    slots["up"].publish(frame("up", NOW_S - 0.25))
    assert Rig(make_config(max_age_s=0.25, max_skew_s=0.5), slots).snapshot(NOW_S).ready
    result = not_ready(Rig(make_config(max_age_s=0.125, max_skew_s=0.5), slots).snapshot(NOW_S))
    assert result.problems("up") == (FaceProblem.STALE,)


def test_every_face_stale_when_time_moves_on(slots: dict[str, LatestSlot]) -> None:
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S + 1.0))
    assert result.faces == FACE_NAMES
    assert {issue.problem for issue in result.issues} == {FaceProblem.STALE}


def test_missing_face(slots: dict[str, LatestSlot]) -> None:
    slots["down"].clear()
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.faces == ("down",) and result.problems("down") == (FaceProblem.MISSING,)


def test_skew_names_the_faces_behind(slots: dict[str, LatestSlot]) -> None:
    # Every face is fresh (age <= 0.3 s), but front and back lag the newest by 0.2 s > 0.15 s.
    slots["front"].publish(frame("front", NOW_S - 0.2))
    slots["back"].publish(frame("back", NOW_S - 0.25))
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.faces == ("front", "back")
    assert {issue.problem for issue in result.issues} == {FaceProblem.SKEWED}
    assert "0.150 s" in result.reason


def test_skew_limit_is_inclusive(slots: dict[str, LatestSlot]) -> None:
    slots["right"].publish(frame("right", NOW_S - 0.125))  # exact in binary
    assert Rig(make_config(max_skew_s=0.125), slots).snapshot(NOW_S).ready
    assert not Rig(make_config(max_skew_s=0.0625), slots).snapshot(NOW_S).ready


def test_unknown_camera_id_is_reported_and_not_used(slots: dict[str, LatestSlot]) -> None:
    slots["left"].publish(frame("left", uid="ffeeddccbbaa998877665544"))
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.faces == ("left",)
    assert result.problems("left") == (FaceProblem.UNKNOWN_CAMERA,)
    assert "ffeeddccbbaa998877665544" in result.reason


def test_face_receiving_another_faces_camera_is_reported(slots: dict[str, LatestSlot]) -> None:
    # Swapped cables: the front device delivers the right camera and vice versa.
    slots["front"].publish(frame("front", uid=UIDS["right"]))
    slots["right"].publish(frame("right", uid=UIDS["front"]))
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.faces == ("front", "right")
    assert result.problems("front") == (FaceProblem.WRONG_CAMERA,)
    assert "configured for face right" in result.reason
    assert "configured for face front" in result.reason


def test_frames_before_hello_are_not_used(slots: dict[str, LatestSlot]) -> None:
    slots["back"].publish(frame("back", uid=None))
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.problems("back") == (FaceProblem.UNIDENTIFIED,)


def test_several_problems_reported_together_in_face_order(slots: dict[str, LatestSlot]) -> None:
    slots["down"].clear()
    slots["front"].publish(frame("front", NOW_S - 0.5))
    slots["up"].publish(frame("up", uid="00" * 12))
    result = not_ready(Rig(make_config(), slots).snapshot(NOW_S))
    assert result.faces == ("front", "up", "down")
    assert [i.problem for i in result.issues] == [
        FaceProblem.STALE,
        FaceProblem.UNKNOWN_CAMERA,
        FaceProblem.MISSING,
    ]


def test_rig_needs_one_source_per_face(slots: dict[str, LatestSlot]) -> None:
    del slots["up"]
    with pytest.raises(ConfigError, match="missing"):
        Rig(make_config(), slots)


def test_capture_clock_maps_camera_time_to_host_time() -> None:
    clock = CaptureClock()
    # Camera clock starts at 0, host at 50 s; transport delay 5 ms, one read delayed by 30 ms.
    delays = [0.005, 0.035, 0.005, 0.005]
    mapped = [clock.to_host(k * 100_000, 50.0 + k * 0.1 + d) for k, d in enumerate(delays)]
    assert mapped[0] == pytest.approx(50.005)
    assert mapped[1] == pytest.approx(50.105, abs=1e-3)  # a late read does not move the capture
    assert mapped[3] == pytest.approx(50.305, abs=1e-3)
    assert all(m <= 50.0 + k * 0.1 + d for k, (m, d) in enumerate(zip(mapped, delays, strict=True)))
    assert clock.to_host(0, 80.0) == 80.0  # camera clock went back (reboot): starts over


# --- boundaries: exactly at each limit and one float step either side ------------------------
# NOW_S - 0.25 and NOW_S - 0.125 are exact in binary, so the age (or spread) is exactly the limit;
# math.nextafter moves the receive time by the smallest step there is.
AGE_LIMIT_S, SKEW_LIMIT_S = 0.25, 0.125


@pytest.mark.parametrize(
    ("receive_s", "fresh"),
    [
        (math.nextafter(NOW_S - AGE_LIMIT_S, math.inf), True),  # one step younger
        (NOW_S - AGE_LIMIT_S, True),  # exactly max_age_s old: the limit is inclusive
        (math.nextafter(NOW_S - AGE_LIMIT_S, -math.inf), False),  # one step older: stale
    ],
)
def test_age_limit_to_the_last_step(
    slots: dict[str, LatestSlot], receive_s: float, fresh: bool
) -> None:
    assert NOW_S - (NOW_S - AGE_LIMIT_S) == AGE_LIMIT_S  # the arithmetic really is exact
    slots["up"].publish(frame("up", receive_s))
    result = Rig(make_config(max_age_s=AGE_LIMIT_S, max_skew_s=0.5), slots).snapshot(NOW_S)
    if fresh:
        assert isinstance(result, RigImage)
    else:
        assert not_ready(result).problems("up") == (FaceProblem.STALE,)


@pytest.mark.parametrize(
    ("receive_s", "within"),
    [
        (math.nextafter(NOW_S - SKEW_LIMIT_S, math.inf), True),  # one step less spread
        (NOW_S - SKEW_LIMIT_S, True),  # exactly max_skew_s behind the newest: inclusive
        (math.nextafter(NOW_S - SKEW_LIMIT_S, -math.inf), False),  # one step more: skewed
    ],
)
def test_skew_limit_to_the_last_step(
    slots: dict[str, LatestSlot], receive_s: float, within: bool
) -> None:
    slots["right"].publish(frame("right", receive_s))  # the others were received at NOW_S
    result = Rig(make_config(max_skew_s=SKEW_LIMIT_S), slots).snapshot(NOW_S)
    if within:
        assert isinstance(result, RigImage)
    else:
        assert not_ready(result).problems("right") == (FaceProblem.SKEWED,)
