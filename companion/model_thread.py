"""The policy's worker: one daemon thread that runs model calls in order, and what a hang leaves.

A model call cannot be interrupted: a call still running when its thread is closed is abandoned,
and recorded, so that `abandoned_inferences()` tells the program whether a hung model is still
running. Such a process must end with `os._exit` after flushing its output: the interpreter's
normal exit runs torch's C++ static destructors under the running call, and Python 3.11 ends a
daemon thread that wakes up during finalization with `pthread_exit`, whose forced unwind through
torch's C++ frames aborts the process ("terminate called without an active exception", SIGABRT;
seen with gdb: `~gil_scoped_release` -> `take_gil` -> `PyThread_exit_thread` while the main
thread runs `TorchLibraryInit::~TorchLibraryInit`). `companion.cli.main` does that.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

_ABANDONED: list[threading.Thread] = []  # model threads left running a call at close


def abandoned_inferences() -> int:
    """How many model calls abandoned at `ModelThread.close` are still running (hung models)."""
    return sum(thread.is_alive() for thread in _ABANDONED)


class ModelThread:
    """One daemon thread that runs submitted calls in order; at most `capacity` waiting.

    A daemon thread (not a ThreadPoolExecutor, whose threads are joined at interpreter exit) so
    that a hung model cannot keep the process from exiting.
    """

    def __init__(self, name: str, capacity: int = 1) -> None:
        self._jobs: queue.Queue[tuple[Callable[[], Any], Future[Any]] | None] = queue.Queue(
            maxsize=capacity
        )
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            fn, future = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller through the future
                future.set_exception(exc)

    def submit(self, fn: Callable[[], Any]) -> Future[Any]:
        """Queue `fn`; raises RuntimeError when closed or full."""
        if self._closed:
            raise RuntimeError("the model thread is closed")
        future: Future[Any] = Future()
        try:
            self._jobs.put_nowait((fn, future))
        except queue.Full:
            raise RuntimeError("the model thread is busy") from None
        return future

    def close(self, timeout_s: float) -> bool:
        """Stop after the running call; True if the thread ended within `timeout_s`.

        A thread still running after that is abandoned (it ends with the process) and counted by
        `abandoned_inferences()`.
        """
        if not self._closed:
            self._closed = True
            try:
                self._jobs.put(None, timeout=timeout_s)
            except queue.Full:
                pass  # a call runs and another waits: the thread is not going to stop now
            else:
                self._thread.join(timeout_s)
        if self._thread.is_alive():
            if self._thread not in _ABANDONED:
                _ABANDONED.append(self._thread)
            return False
        return True
