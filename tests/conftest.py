"""Shared pytest fixtures.

Set-ups made once a session and shared read-only (a test that changes one copies it first):
``simulated(**options)`` (any simulated raw flight, one per set of options), ``small_flight`` /
``small_flights(seed)``, ``strips_flight``, ``tiny_flights(seed)``, the terrain flights ``hills`` and
``ridge`` (shapes in ``helpers.py``), ``small_archive``; ``local_cluster`` / ``scheduler``: one
LocalCluster shaped like ``archive render``'s own for the tests that render through ``--scheduler``.
Constants and small helpers are in ``helpers.py`` (``from helpers import FOV``)."""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import pytest
import rioxarray  # noqa: F401  (registers .rio for tests reading outputs; the render no longer imports it)

from helpers import FOV, HILLS, RIDGE, SMALL_FLIGHT, STRIPS_FLIGHT, TINY_FLIGHT

RESONON_SAMPLES = Path(__file__).resolve().parents[1].parent / "shared" / "samples" / "resonon"


@pytest.fixture
def resonon_samples() -> Path:
    """Folder of real Resonon/Spectronon files (read only, never copied); skips when absent."""
    if not RESONON_SAMPLES.is_dir():
        pytest.skip(f"real Resonon samples not found at {RESONON_SAMPLES}")
    return RESONON_SAMPLES


@pytest.fixture(scope="session")
def simulated(tmp_path_factory):
    """``simulated(**options) -> (directory, Truth)``: a simulated raw flight (``simulate_flight``'s
    options, seed included), made once per session for each set of options and shared read-only by
    the tests that ask for it; a test that changes a flight copies it first (``shutil.copytree``)."""
    from archive.simulator.command import simulate_flight

    made: dict = {}

    def simulate(**options):
        key = tuple(sorted(options.items()))
        if key not in made:
            # named by seed: a batch of one shape's seeds writes one output a flight, named by its folder
            directory = tmp_path_factory.mktemp("simulated") / f"flight{options.get('seed', 0)}"
            made[key] = directory, simulate_flight(directory, **options)
        return made[key]

    return simulate


@pytest.fixture(scope="session")
def small_flights(simulated):
    """``small_flights(seed) -> directory``: the :data:`helpers.SMALL_FLIGHT` flight of that seed."""
    return lambda seed: simulated(seed=seed, **SMALL_FLIGHT)[0]


@pytest.fixture(scope="session")
def small_flight(small_flights) -> Path:
    """The small simulated raw flight (:data:`helpers.SMALL_FLIGHT`, seed 0), shared read-only."""
    return small_flights(0)


@pytest.fixture(scope="session")
def small_archive(small_flight, tmp_path_factory) -> tuple[Path, str]:
    """(archive, collection id) of :func:`small_flight` ingested (field of view :data:`helpers.FOV`);
    tests read it and write their outputs elsewhere."""
    from archive.ingest.command import ingest

    arc = tmp_path_factory.mktemp("small_archive") / "arc"
    (r,) = ingest([str(small_flight)], arc, FOV, progress=False)
    return arc, r.cid


@pytest.fixture(scope="session")
def strips_flight(simulated):
    """(directory, Truth) of the :data:`helpers.STRIPS_FLIGHT` flight (4 cubes in 2 strips), shared read-only."""
    return simulated(**STRIPS_FLIGHT)


def _terrain(simulated, options: dict):
    from archive.simulator.truth import load_truth

    directory, _ = simulated(**options)
    return directory, load_truth(directory)


@pytest.fixture(scope="session")
def hills(simulated):
    """(directory, Truth as loaded from it) of the :data:`helpers.HILLS` terrain flight (its DEM
    ``dem.tif`` inside), shared read-only."""
    return _terrain(simulated, HILLS)


@pytest.fixture(scope="session")
def ridge(simulated):
    """(directory, Truth as loaded from it) of the :data:`helpers.RIDGE` terrain flight, shared read-only."""
    return _terrain(simulated, RIDGE)


@pytest.fixture(scope="session")
def tiny_flights(simulated):
    """``tiny_flights(seed) -> directory``: the :data:`helpers.TINY_FLIGHT` flight of that seed."""
    return lambda seed: simulated(seed=seed, **TINY_FLIGHT)[0]


@pytest.fixture(scope="session")
def local_cluster():
    """A LocalCluster shaped like ``archive render``'s own (1 spawned worker, 2 threads, GPU=2), shared
    by the tests that render through ``--scheduler`` and leave its workers as they are (a test that
    kills, restarts or reconfigures workers starts its own). Its scheduler runs in this process."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, resources={"GPU": 2},
                      dashboard_address=":0", silence_logs=logging.ERROR) as cluster:
        yield cluster


@pytest.fixture(scope="session")
def scheduler(local_cluster) -> str:
    """The address of :func:`local_cluster`'s scheduler (for ``--scheduler``)."""
    return local_cluster.scheduler_address


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
