"""Shared pytest fixtures."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest
import rioxarray  # noqa: F401  (registers .rio for tests reading outputs; the render no longer imports it)

RESONON_SAMPLES = Path(__file__).resolve().parents[1].parent / "shared" / "samples" / "resonon"


@pytest.fixture
def resonon_samples() -> Path:
    """Folder of real Resonon/Spectronon files (read only, never copied); skips when absent."""
    if not RESONON_SAMPLES.is_dir():
        pytest.skip(f"real Resonon samples not found at {RESONON_SAMPLES}")
    return RESONON_SAMPLES


#: The shape of the small flight the concurrency and fault tests share (2 cubes on one pass).
SMALL_FLIGHT = dict(cubes=2, bands=4, samples=64, lines=100, cubes_per_pass=2)


@pytest.fixture(scope="session")
def small_flight(tmp_path_factory) -> Path:
    """A small simulated raw flight (:data:`SMALL_FLIGHT`, seed 0), shared read-only by the tests."""
    from archive.simulator.command import simulate_flight

    d = tmp_path_factory.mktemp("small_flight") / "flight"
    simulate_flight(d, seed=0, **SMALL_FLIGHT)
    return d


@pytest.fixture(scope="session")
def small_archive(small_flight, tmp_path_factory) -> tuple[Path, str]:
    """(archive, collection id) of :func:`small_flight` ingested (field of view 47.5 degrees); tests
    read it and write their outputs elsewhere."""
    from archive.ingest.command import ingest

    arc = tmp_path_factory.mktemp("small_archive") / "arc"
    (r,) = ingest([str(small_flight)], arc, 47.5, progress=False)
    return arc, r.cid


@contextlib.contextmanager
def serve_loopback(app, backlog: int = 16):
    """Serve the ASGI ``app`` with a real uvicorn server on a free loopback port, in a thread; yields
    its base URL ``http://127.0.0.1:PORT``; stops the server on exit."""
    import socket
    import threading
    import time

    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(backlog)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.02)
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


@contextlib.contextmanager
def archive_view(command: list[str], cwd: str | Path, env: dict | None = None, timeout: float = 60):
    """Run ``command`` (an ``archive view ... --port 0`` command line) as a subprocess; yields (its URL
    ``http://127.0.0.1:PORT/``, the Popen) once it printed its address; on exit sends SIGINT (the
    server's own shutdown), killing it after 15 s. The caller may check ``proc.returncode`` afterwards."""
    import os
    import queue
    import re
    import signal
    import subprocess
    import threading

    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True).start()
    try:
        try:
            line = lines.get(timeout=timeout)
        except queue.Empty:
            proc.kill()
            pytest.fail(f"archive view printed nothing: {proc.stderr.read()}")
        found = re.search(r"http://127\.0\.0\.1:\d+/", line)
        assert found, line
        yield found.group(0), proc
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
