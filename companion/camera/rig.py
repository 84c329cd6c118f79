"""The camera rig: six latest-frame sources -> one fresh, consistent 64x384 image, or why not.

Pure logic: `Rig.snapshot(now_s)` reads each face's `FrameSource.latest()` and applies, per face
in `FACE_NAMES` order:

1. a frame must exist (`MISSING`);
2. it must come from an identified camera (`UNIDENTIFIED`: no HELLO yet on that connection);
3. that camera must be the one configured for the face (`UNKNOWN_CAMERA`: its id is in no face's
   map; `WRONG_CAMERA`: its id belongs to another face, e.g. swapped cables or udev names);
4. it must be fresh: `now_s - receive_time_s <= max_age_s` (`STALE`);

and across the faces that pass 1-4, receive times must spread by at most `max_skew_s`: faces
received more than `max_skew_s` before the newest one are `SKEWED`. A face that fails any rule is
never stitched. All times are seconds of the host monotonic clock (the one the links use).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.camera.config import CameraRigConfig
from companion.camera.layout import FACE_NAMES, stitch
from companion.camera.slot import CameraFrame, FrameSource
from companion.errors import ConfigError


class FaceProblem(Enum):
    """Why a face cannot be used this tick."""

    MISSING = "missing"
    UNIDENTIFIED = "unidentified"
    UNKNOWN_CAMERA = "unknown camera"
    WRONG_CAMERA = "wrong camera"
    STALE = "stale"
    SKEWED = "skewed"


@dataclass(frozen=True)
class FaceIssue:
    """One face's problem, with a human-readable detail naming ids, ages and limits."""

    face: str
    problem: FaceProblem
    detail: str

    def __str__(self) -> str:
        return f"{self.face}: {self.problem.value} ({self.detail})"


@dataclass(frozen=True, eq=False)
class RigImage:
    """A ready snapshot: the stitched image and, per face in `FACE_NAMES` order, its frame's data.

    Times in seconds of the host monotonic clock.
    """

    image: NDArray[np.uint8]  # (64, 384) uint8, layout.stitch of the six tiles
    receive_times_s: tuple[float, ...]  # per face
    capture_times_s: tuple[float, ...]  # per face, camera capture times mapped to the host clock
    seqs: tuple[int, ...]  # per face, camera sequence numbers
    camera_uids: tuple[str, ...]  # per face

    @property
    def oldest_capture_time_s(self) -> float:
        """Earliest capture among the six tiles: the time to read the attitude at."""
        return min(self.capture_times_s)

    @property
    def oldest_receive_time_s(self) -> float:
        """Earliest receive time among the six tiles."""
        return min(self.receive_times_s)

    @property
    def ready(self) -> bool:
        """Always True (lets callers branch on `snapshot(...).ready`)."""
        return True


@dataclass(frozen=True)
class RigNotReady:
    """No usable image this tick; `issues` names every face that failed and why."""

    issues: tuple[FaceIssue, ...]

    @property
    def faces(self) -> tuple[str, ...]:
        """Names of the faces with at least one issue, in `FACE_NAMES` order, no repeats."""
        named = {issue.face for issue in self.issues}
        return tuple(face for face in FACE_NAMES if face in named)

    def problems(self, face: str) -> tuple[FaceProblem, ...]:
        """The problems reported for one face."""
        return tuple(issue.problem for issue in self.issues if issue.face == face)

    @property
    def reason(self) -> str:
        """One line for logs and telemetry, e.g. "front: stale (age 0.42 s > 0.30 s)"."""
        return "; ".join(str(issue) for issue in self.issues)

    @property
    def ready(self) -> bool:
        """Always False."""
        return False


RigSnapshot = RigImage | RigNotReady


class Rig:
    """Checks and stitches the six faces' latest frames. Holds no state besides its sources."""

    def __init__(self, config: CameraRigConfig, sources: Mapping[str, FrameSource]) -> None:
        """`sources`: one `FrameSource` per face name in `FACE_NAMES` (e.g. the serial links)."""
        missing = [face for face in FACE_NAMES if face not in sources]
        extra = sorted(set(sources) - set(FACE_NAMES))
        if missing or extra:
            raise ConfigError(
                f"rig sources: need exactly the faces {', '.join(FACE_NAMES)}; "
                f"missing {missing or 'none'}, unknown {extra or 'none'}"
            )
        self._config = config
        self._sources = {face: sources[face] for face in FACE_NAMES}

    @property
    def sources(self) -> Mapping[str, FrameSource]:
        """The frame source of each face (FACE_NAMES order)."""
        return self._sources

    @property
    def config(self) -> CameraRigConfig:
        """The rig configuration (ids, freshness limits)."""
        return self._config

    def latest_seqs(self) -> tuple[int | None, ...]:
        """The sequence number of each face's latest frame (None: none yet), FACE_NAMES order."""
        frames = (self._sources[face].latest() for face in FACE_NAMES)
        return tuple(None if frame is None else frame.seq for frame in frames)

    def has_new_set(self, seen: tuple[int | None, ...] | None) -> bool:
        """Whether every face holds a frame other than the one it held when `seen` was taken
        (`latest_seqs()` at the previous tick): a complete fresh set to look at."""
        for index, seq in enumerate(self.latest_seqs()):
            if seq is None or (seen is not None and seq == seen[index]):
                return False
        return True

    def snapshot(self, now_s: float) -> RigSnapshot:
        """A `RigImage` if all six faces pass the rules at host time `now_s`, else `RigNotReady`."""
        frames: dict[str, CameraFrame] = {}
        issues: list[FaceIssue] = []
        for face in FACE_NAMES:
            frame = self._sources[face].latest()
            issue = self._check_face(face, frame, now_s)
            if issue is not None:
                issues.append(issue)
            elif frame is not None:
                frames[face] = frame
        issues.extend(self._check_skew(frames))
        if issues:
            issues.sort(key=lambda issue: FACE_NAMES.index(issue.face))
            return RigNotReady(tuple(issues))
        ordered = [frames[face] for face in FACE_NAMES]
        return RigImage(
            image=stitch([frame.image for frame in ordered]),
            receive_times_s=tuple(frame.receive_time_s for frame in ordered),
            capture_times_s=tuple(frame.capture_time_s for frame in ordered),
            seqs=tuple(frame.seq for frame in ordered),
            camera_uids=tuple(str(frame.camera_uid) for frame in ordered),
        )

    def _check_face(self, face: str, frame: CameraFrame | None, now_s: float) -> FaceIssue | None:
        if frame is None:
            return FaceIssue(face, FaceProblem.MISSING, "no frame received yet")
        expected = self._config.faces[face].camera_id
        uid = frame.camera_uid
        if uid is None:
            detail = f"{frame.device}: frames but no HELLO yet; expected camera {expected}"
            return FaceIssue(face, FaceProblem.UNIDENTIFIED, detail)
        if uid != expected:
            owner = self._config.face_of_camera(uid)
            if owner is None:
                detail = f"{frame.device} delivers camera {uid} (in no face's map), not {expected}"
                return FaceIssue(face, FaceProblem.UNKNOWN_CAMERA, detail)
            detail = f"{frame.device} delivers camera {uid}, configured for face {owner}"
            return FaceIssue(face, FaceProblem.WRONG_CAMERA, detail)
        age_s = now_s - frame.receive_time_s
        if age_s > self._config.max_age_s:
            detail = f"age {age_s:.3f} s > {self._config.max_age_s:.3f} s"
            return FaceIssue(face, FaceProblem.STALE, detail)
        return None

    def _check_skew(self, frames: Mapping[str, CameraFrame]) -> list[FaceIssue]:
        if len(frames) < 2:
            return []
        newest_s = max(frame.receive_time_s for frame in frames.values())
        limit_s = self._config.max_skew_s
        issues = []
        for face, frame in frames.items():
            behind_s = newest_s - frame.receive_time_s
            if behind_s > limit_s:
                detail = f"received {behind_s:.3f} s before the newest face > {limit_s:.3f} s"
                issues.append(FaceIssue(face, FaceProblem.SKEWED, detail))
        return issues
