"""Shared pytest fixtures."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

RESONON_SAMPLES = Path(__file__).resolve().parents[1].parent / "shared" / "samples" / "resonon"


@pytest.fixture
def resonon_samples() -> Path:
    """Folder of real Resonon/Spectronon files (read only, never copied); skips when absent."""
    if not RESONON_SAMPLES.is_dir():
        pytest.skip(f"real Resonon samples not found at {RESONON_SAMPLES}")
    return RESONON_SAMPLES


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
