"""The viewer's one render thread: every OpenGL call runs on it, one job at a time, the latest
view's first.

A GL context belongs to the thread that made it (``archive.render.context``), so the server hands
all drawing to one thread of its own instead of the event loop's thread pool. Jobs wait in a
priority queue: the highest ``priority`` first (the server gives each request its view's
generation, so after fast changes the newest picture is drawn before the superseded ones still
queued), in submission order among equals. Each job can be cancelled while it waits (its request
was abandoned: the browser dropped a tile that left the view, or a picture nobody waits for any
more): it is then skipped without drawing, and a running job stops at its next :meth:`Job.check`
(between cubes).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math
import threading
from collections.abc import Awaitable, Callable
from concurrent.futures import Future

__all__ = ["Cancelled", "Job", "RenderThread"]


class Cancelled(Exception):
    """A job whose request was abandoned before it drew."""


class Job:
    """One unit of drawing: ``future`` gives its result; :meth:`cancel` abandons it."""

    def __init__(self, priority: float = 0.0):
        self.cancelled = threading.Event()
        self.future: Future = Future()
        self.priority = float(priority)

    def cancel(self) -> None:
        self.cancelled.set()

    def check(self) -> None:
        """Raise :class:`Cancelled` when the job was abandoned (called by the drawing code)."""
        if self.cancelled.is_set():
            raise Cancelled()


class RenderThread:
    """A single worker thread for GL jobs, the highest priority first, with counters: ``done``
    (finished), ``skipped`` (cancelled before they started), ``stopped`` (cancelled while drawing),
    ``failed``, ``overtaken`` (jobs that ran before one submitted earlier: a newer view first)."""

    def __init__(self, name: str = "archive-view-render"):
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)
        self._heap: list = []
        self._seq = itertools.count()
        self._closed = False
        self.counts = {"submitted": 0, "done": 0, "skipped": 0, "stopped": 0, "failed": 0, "overtaken": 0}
        self._queued = 0
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _count(self, key: str, delta: int = 1) -> None:
        with self._lock:
            self.counts[key] += delta

    @property
    def queued(self) -> int:
        """Jobs submitted and not finished yet."""
        with self._lock:
            return self._queued

    def submit(self, fn: Callable, *args, priority: float = 0.0) -> Job:
        """Run ``fn(*args, check=job.check)`` on the render thread unless cancelled first; jobs of
        a higher ``priority`` (e.g. a later view generation) run before those waiting with a lower one."""
        job = Job(priority)
        with self._lock:
            if self._closed:
                raise RuntimeError("the render thread has been shut down")
            self._queued += 1
            self.counts["submitted"] += 1
            heapq.heappush(self._heap, (-job.priority, next(self._seq), job, fn, args))
            self._ready.notify()
        return job

    def _loop(self) -> None:
        last = -1
        while True:
            with self._lock:
                while not self._heap and not self._closed:
                    self._ready.wait()
                if not self._heap:
                    return
                _, seq, job, fn, args = heapq.heappop(self._heap)
                if seq < last:
                    self.counts["overtaken"] += 1
                last = max(last, seq)
            self._run(job, fn, args)

    def _run(self, job: Job, fn: Callable, args: tuple) -> None:
        try:
            if not job.future.set_running_or_notify_cancel():
                self._count("skipped")
                return
            if job.cancelled.is_set():
                self._count("skipped")
                job.future.set_exception(Cancelled())
                return
            try:
                result = fn(*args, check=job.check)
            except Cancelled as exc:
                self._count("stopped")
                job.future.set_exception(exc)
            except BaseException as exc:  # noqa: BLE001 - handed to the waiting request
                self._count("failed")
                job.future.set_exception(exc)
            else:
                self._count("done")
                job.future.set_result(result)
        finally:
            with self._lock:
                self._queued -= 1

    async def run(self, fn: Callable, *args, abandoned: Callable[[], Awaitable[bool]] | None = None,
                  poll_s: float = 0.05, priority: float = 0.0):
        """Await ``fn(*args, check=...)`` on the render thread (``priority``: :meth:`submit`). While
        it waits, ``abandoned()`` is polled every ``poll_s`` seconds; when it says True the job is
        cancelled and :class:`Cancelled` raised here (nothing is drawn for an abandoned request)."""
        job = self.submit(fn, *args, priority=priority)
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
        """Run ``fn(*args)`` on the render thread before anything queued, and wait for it
        (blocking; for set-up and tests)."""
        return self.submit(lambda *a, check: fn(*a), *args, priority=math.inf).future.result()

    def shutdown(self) -> None:
        """Cancel what has not started and stop the thread (after the running job)."""
        with self._lock:
            self._closed = True
            pending, self._heap = self._heap, []
            self._ready.notify_all()
        for _, _, job, _, _ in pending:
            job.future.cancel()
            self._count("skipped")
            with self._lock:
                self._queued -= 1
        if threading.current_thread() is not self._thread:
            self._thread.join()
