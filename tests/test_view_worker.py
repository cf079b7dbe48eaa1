"""The viewer's render thread (:mod:`archive.view.worker`): the latest view's jobs first, abandoned
jobs skipped, set-up calls before anything queued; and how a request's priority is read."""

from __future__ import annotations

import threading
import time

import pytest

from archive.view.jobs import view_generation
from archive.view.worker import Cancelled, RenderThread


def _wait(predicate, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def _block(render: RenderThread, gate: threading.Event) -> None:
    """Occupy the render thread until ``gate`` is set (returns once the job has started)."""
    started = threading.Event()
    render.submit(lambda check: (started.set(), gate.wait(10)))
    assert started.wait(10)


def test_the_latest_generation_runs_first_and_abandoned_jobs_are_skipped():
    render = RenderThread()
    try:
        gate, ran = threading.Event(), []
        _block(render, gate)   # busy: everything below waits in the queue
        jobs = [render.submit(lambda name, check: ran.append(name), name, priority=p)
                for name, p in [("a1", 1), ("b1", 1), ("c3", 3), ("d2", 2), ("e3", 3)]]
        jobs[1].cancel()   # its request was abandoned while it waited
        assert render.queued == 6
        gate.set()
        for job in jobs:
            try:
                job.future.result(10)
            except Cancelled:
                assert job is jobs[1]
        # newest generation first, submission order among equals; the abandoned one never ran
        assert ran == ["c3", "e3", "d2", "a1"]
        assert render.counts["skipped"] == 1 and render.counts["done"] == 5 and render.queued == 0
        assert render.counts["overtaken"] == 3   # d2, b1 and a1 ran (or were dropped) after e3
    finally:
        render.shutdown()


def test_calls_run_before_the_queue_and_shutdown_cancels_what_waits():
    render = RenderThread()
    gate, ran = threading.Event(), []
    _block(render, gate)
    waiting = render.submit(lambda check: ran.append("queued"), priority=1e15)
    caller = threading.Thread(target=lambda: render.call(lambda: ran.append("call")))
    caller.start()
    _wait(lambda: render.queued == 3)
    gate.set()
    caller.join(10)
    waiting.future.result(10)
    assert ran == ["call", "queued"]
    gate.clear()
    _block(render, gate)
    left = render.submit(lambda check: ran.append("never"))
    stopper = threading.Thread(target=render.shutdown)
    stopper.start()
    _wait(lambda: left.future.cancelled())
    gate.set()
    stopper.join(10)
    assert not stopper.is_alive() and "never" not in ran
    with pytest.raises(RuntimeError, match="shut down"):
        render.submit(lambda check: None)


def test_view_generation_header():
    assert view_generation("1700000000123.5") == 1700000000123.5
    # absent, not a number or not finite: the arrival time, ms
    for header in (None, "soon", "inf", "nan", ""):
        assert view_generation(header, now=12.5) == 12500.0
