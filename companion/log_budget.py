"""The flight-log folder's housekeeping: which file is being written, and a disk budget.

The recorder holds an exclusive `flock` on the file it is writing for as long as it writes it
(released when it closes the file or when the process dies, however it dies). So "is this log
being written?" has an exact answer, here (`is_being_written`) and on the drone's shell
(`flock -n -s FILE true` fails), which the ground station uses to skip it when pulling logs.

`prune_logs` deletes the oldest closed `*.mcap` files of a folder until the ones left plus the
room reserved for the next file fit the budget (`[recorder] max_total_mb`). A file some process
is writing is never deleted.
"""

from __future__ import annotations

import fcntl
import logging
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"  # opens every MCAP file and closes every complete one


def lock_for_writing(stream: IO[bytes]) -> None:
    """Mark an open log as being written (advisory lock, held until the stream is closed).

    A file system without locks (some network mounts) only loses that mark: logged, not raised.
    """
    try:
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        log.warning("recorder: cannot lock %s as being written: %s", stream.name, exc)


def is_being_written(path: Path) -> bool:
    """True while a recorder (in any process) holds `path` open for writing."""
    try:
        with open(path, "rb") as stream:
            try:
                fcntl.flock(stream.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(stream.fileno(), fcntl.LOCK_UN)
    except OSError:
        return False  # gone, or not ours to read: not a log being written that we could delete
    return False


@dataclass(frozen=True)
class DeletedLog:
    """A log removed to keep the folder within its budget."""

    path: Path
    size_bytes: int


@dataclass(frozen=True)
class PruneResult:
    deleted: tuple[DeletedLog, ...]
    total_bytes: int  # the `*.mcap` files left in the folder
    fits: bool  # total + reserve within the budget


def prune_logs(
    directory: Path,
    *,
    budget_bytes: float,
    reserve_bytes: float,
    keep: Collection[Path] = (),
) -> PruneResult:
    """Delete the oldest `*.mcap` files (modification time, then name) until the rest plus
    `reserve_bytes` (the next file's largest size) fit `budget_bytes`.

    Files in `keep` and files being written are never deleted; a file that cannot be deleted is
    logged and skipped.
    """
    logs: list[tuple[float, str, Path, int]] = []
    for path in directory.glob("*.mcap"):
        try:
            stat = path.stat()
        except OSError:
            continue  # deleted meanwhile
        logs.append((stat.st_mtime, path.name, path, stat.st_size))
    logs.sort()
    total = sum(size for *_, size in logs)
    keep_resolved = {Path(p).resolve() for p in keep}
    deleted: list[DeletedLog] = []
    for _, _, path, size in logs:
        if total + reserve_bytes <= budget_bytes:
            break
        if path.resolve() in keep_resolved or is_being_written(path):
            continue
        try:
            path.unlink()
        except OSError as exc:
            log.warning("recorder: cannot delete %s to stay within the budget: %s", path, exc)
            continue
        total -= size
        deleted.append(DeletedLog(path, size))
    return PruneResult(tuple(deleted), total, total + reserve_bytes <= budget_bytes)


def make_room(
    directory: Path, max_total_mb: float | None, max_file_mb: float
) -> list[dict[str, Any]]:
    """Before a new log opens: prune to fit one more `max_file_mb` file within `max_total_mb`
    (None: no budget). Returns the health events (`level`, `event`, `detail`) to record."""
    if max_total_mb is None:
        return []
    result = prune_logs(directory, budget_bytes=max_total_mb * 1e6, reserve_bytes=max_file_mb * 1e6)
    reason = f"recorder.max_total_mb {max_total_mb:g} MB"
    events: list[dict[str, Any]] = []
    for gone in result.deleted:
        size_mb = gone.size_bytes / 1e6
        log.warning("recorder: deleted %s (%.1f MB): %s", gone.path, size_mb, reason)
        detail = {"file": gone.path.name, "size_mb": round(size_mb, 3), "reason": reason}
        events.append({"level": "warning", "event": "log deleted", "detail": detail})
    if not result.fits:
        total_mb = result.total_bytes / 1e6
        log.warning(
            "recorder: %.1f MB of logs left plus the next file exceed %s (nothing more to delete)",
            total_mb,
            reason,
        )
        detail = {"total_mb": round(total_mb, 3), "max_total_mb": max_total_mb}
        events.append({"level": "warning", "event": "log budget exceeded", "detail": detail})
    return events
