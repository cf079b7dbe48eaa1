"""The viewer's one render thread: every OpenGL call runs on it, one job at a time, in order.

A GL context belongs to the thread that made it (``archive.render.context``), so the server hands
all drawing to a single-thread executor instead of the event loop's thread pool. Each job can be
cancelled while it waits (its request was abandoned: the browser dropped a tile that left the
view): it is then skipped without drawing, and a running job stops at its next
:meth:`Job.check` (between cubes).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["Cancelled", "Job", "RenderThread"]


class Cancelled(Exception):
    """A job whose request was abandoned before it drew."""


class Job:
    """One unit of drawing: ``future`` gives its result; :meth:`cancel` abandons it."""

    def __init__(self):
        self.cancelled = threading.Event()
        self.future: Future | None = None

    def cancel(self) -> None:
        self.cancelled.set()

    def check(self) -> None:
        """Raise :class:`Cancelled` when the job was abandoned (called by the drawing code)."""
        if self.cancelled.is_set():
            raise Cancelled()


class RenderThread:
    """A single worker thread for GL jobs, with counters: ``done`` (finished), ``skipped``
    (cancelled before they started), ``stopped`` (cancelled while drawing), ``failed``."""

    def __init__(self, name: str = "archive-view-render"):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._lock = threading.Lock()
        self.counts = {"submitted": 0, "done": 0, "skipped": 0, "stopped": 0, "failed": 0}
        self._queued = 0

    def _count(self, key: str, delta: int = 1) -> None:
        with self._lock:
            self.counts[key] += delta

    @property
    def queued(self) -> int:
        """Jobs submitted and not finished yet."""
        with self._lock:
            return self._queued

    def submit(self, fn: Callable, *args) -> Job:
        """Run ``fn(*args, check=job.check)`` on the render thread unless cancelled first."""
        job = Job()

        def run():
            try:
                if job.cancelled.is_set():
                    self._count("skipped")
                    raise Cancelled()
                try:
                    result = fn(*args, check=job.check)
                except Cancelled:
                    self._count("stopped")
                    raise
                except BaseException:
                    self._count("failed")
                    raise
                self._count("done")
                return result
            finally:
                with self._lock:
                    self._queued -= 1

        with self._lock:
            self._queued += 1
            self.counts["submitted"] += 1
        job.future = self._pool.submit(run)
        return job

    async def run(self, fn: Callable, *args, abandoned: Callable[[], Awaitable[bool]] | None = None,
                  poll_s: float = 0.05):
        """Await ``fn(*args, check=...)`` on the render thread. While it waits, ``abandoned()`` is
        polled every ``poll_s`` seconds; when it says True the job is cancelled and
        :class:`Cancelled` raised here (nothing is drawn for an abandoned request)."""
        job = self.submit(fn, *args)
        waiting = asyncio.wrap_future(job.future)
        while True:
            done, _ = await asyncio.wait({waiting}, timeout=poll_s)
            if done:
                return waiting.result()
            if abandoned is not None and await abandoned():
                job.cancel()
                # The job ends soon (skipped, or stopped at its next check); its outcome is not needed.
                waiting.add_done_callback(lambda f: f.cancelled() or f.exception())
                raise Cancelled()

    def call(self, fn: Callable, *args):
        """Run ``fn(*args)`` on the render thread and wait for it (blocking; for set-up and tests)."""
        return self._pool.submit(fn, *args).result()

    def shutdown(self) -> None:
        """Cancel what has not started and stop the thread (after the running job)."""
        self._pool.shutdown(wait=True, cancel_futures=True)
