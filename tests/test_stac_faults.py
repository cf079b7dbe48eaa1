"""Untrusted input to the STAC API of ``archive view`` (issue 30, finding 1): a filter nested 2,000
parentheses deep used to kill the server (SIGSEGV in the cql2 parser, exit 139); deep NOT nesting
and ``{"limit": 1e999}`` gave 500s. Here a real ``archive view`` process (started by the test on
127.0.0.1) gets those requests and a bounded fuzz of others (nesting up to 100,000, huge numbers,
random bytes); after each the process must still be alive, the answer a 400 with a message, and
the next normal search must work."""

from __future__ import annotations

import json
import random
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from archive.ingest.command import ingest
from archive.simulator.command import simulate_flight
from helpers import FOV

ENDPOINTS = ("GET /stac/search", "GET /stac/collections/flights/items", "POST /stac/search")


@pytest.fixture(scope="module")
def archive_dir(tmp_path_factory) -> Path:
    """An archive holding one small simulated flight."""
    base = tmp_path_factory.mktemp("stac_faults")
    truth = simulate_flight(base / "flight", cubes=1, samples=32, lines=120, seed=3, start="2024-06-12T16:00:00Z")
    ingest([str(base / "flight")], base / "archive", FOV, ground_height=truth.ground_height, progress=False)
    return base / "archive"


def start_view(archive: Path, *extra: str, env: dict | None = None, user: list[str] | None = None):
    """``archive view --archive ARCHIVE --port 0`` as a process of its own; (process, base URL)."""
    args = [*(user or []), sys.executable, "-m", "archive", "view", "--archive", str(archive), "--port", "0", *extra]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    line = proc.stdout.readline()
    if " at http://" not in line:
        proc.kill()
        raise AssertionError(f"archive view did not start: {line!r} {proc.stderr.read()[-2000:]}")
    url = line.split(" at ", 1)[1].split()[0].rstrip("/")
    return proc, url


def stop_view(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


@pytest.fixture(scope="module")
def server(archive_dir):
    proc, url = start_view(archive_dir)
    yield proc, url
    stop_view(proc)


def request(url: str, method: str = "GET", body: bytes | None = None, timeout: float = 60) -> tuple[int, dict]:
    """(status, JSON answer) of one request; {"text": ...} when the answer is not JSON (uvicorn
    answers a request line longer than it reads, 16 KiB, with a plain-text 400 and closes the
    connection, maybe before the client has read it)."""
    req = urllib.request.Request(url, data=body, method=method,
                                 headers={"Content-Type": "application/json"} if body is not None else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            status, raw = r.status, r.read()
    except urllib.error.HTTPError as exc:
        status = exc.code
        try:
            raw = exc.read()
        except ConnectionError:
            raw = exc.reason.encode() if isinstance(exc.reason, str) else b""
    try:
        return status, json.loads(raw)
    except ValueError:
        return status, {"text": raw.decode("latin-1")}


def search(base: str, endpoint: str, filter_text: str | None = None, body: dict | bytes | None = None,
           params: dict | None = None) -> tuple[int, dict]:
    """One search through ``endpoint`` (one of ENDPOINTS) with a cql2-text filter or a raw body."""
    method, path = endpoint.split(" ")
    if method == "POST":
        if body is None:
            body = {"filter": filter_text, "filter-lang": "cql2-text", **(params or {})}
        raw = body if isinstance(body, bytes) else json.dumps(body).encode()
        return request(base + path, "POST", raw)
    query = dict(params or {})
    if filter_text is not None:
        query["filter"] = filter_text
    return request(f"{base}{path}?{urllib.parse.urlencode(query)}")


def assert_alive(proc: subprocess.Popen, base: str) -> None:
    """The server process runs and answers a normal search with its flight."""
    assert proc.poll() is None, f"archive view died with exit code {proc.returncode}"
    status, doc = request(f"{base}/stac/search?limit=5")
    assert status == 200 and len(doc["features"]) == 1, (status, doc)


@pytest.mark.parametrize("endpoint", ENDPOINTS)
def test_nested_parentheses_answer_400_and_the_server_lives(server, endpoint):
    """The request of finding 1: ~2,000 nested parentheses (~4 KB) in a cql2-text filter."""
    proc, base = server
    deep = "(" * 2000 + "id = 'x'" + ")" * 2000
    status, doc = search(base, endpoint, deep)
    assert status == 400, (status, doc)
    assert "nested" in doc["description"] and doc["code"] == "InvalidParameterValue"
    assert_alive(proc, base)
    # a filter of reasonable depth still works (and finds the flight)
    status, doc = search(base, endpoint, "(" * 20 + "gsd > 0" + ")" * 20)
    assert status == 200 and len(doc["features"]) == 1, (status, doc)


def test_deep_not_and_huge_numbers_are_400_not_500(server):
    proc, base = server
    cases = [
        ("GET /stac/search", "NOT " * 3000 + "id = 'x'", None),
        ("GET /stac/search", " AND ".join(["NOT (id = 'x')"] * 300), None),
        ("GET /stac/search", "gsd < 1e999", None),
        ("GET /stac/search", "gsd = " + "-" * 5000 + "1", None),
        ("GET /stac/search", "gsd = " + "+".join(["1"] * 3000), None),
        ("POST /stac/search", None, b'{"limit": 1e999}'),
        ("POST /stac/search", None, b'{"limit": -1e999}'),
        ("POST /stac/search", None, b'{"limit": ' + b"9" * 400 + b"}"),
        ("POST /stac/search", None, b'{"limit": 12345678901234567890123}'),
        ("POST /stac/search", None, b'{"limit": 2.5}'),
        ("POST /stac/search", None, b'{"bbox": [-1e999, 0, 1, 1]}'),
        ("POST /stac/search", None, b'{"bbox": [' + b"9" * 400 + b', 0, 1, 1]}'),
        ("POST /stac/search", None, b'{"token": "o' + b"9" * 40 + b'"}'),
        ("POST /stac/search", None, b'{"filter-lang": "cql2-json", "filter": ' + _json_not(5000) + b"}"),
        ("POST /stac/search", None, json.dumps({"intersects": {"type": "Point", "coordinates": [1e300, 0]}}).encode()),
    ]
    for endpoint, text, body in cases:
        status, doc = search(base, endpoint, text, body)
        assert status == 400, (endpoint, (text or body)[:60], status, doc)
        assert doc.get("description"), doc
    for params in ({"limit": "1e999"}, {"limit": "9" * 400}, {"token": "o" + "9" * 400}):
        status, doc = request(f"{base}/stac/search?{urllib.parse.urlencode(params)}")
        assert status == 400, (params, status, doc)
    assert_alive(proc, base)


def _json_not(depth: int) -> bytes:
    """cql2-json text of ``depth`` nested NOTs (written as text: json.dumps itself would recurse)."""
    return b'{"op": "not", "args": [' * depth + b'{"op": "=", "args": [{"property": "id"}, "x"]}' + b"]}" * depth


def _fuzz_inputs(rng: random.Random) -> list[tuple[str, str | None, bytes | None]]:
    """(endpoint, cql2-text filter or None, raw POST body or None): bounded, seeded."""
    out: list[tuple[str, str | None, bytes | None]] = []
    for depth in (65, 100, 1000, 2000, 10_000, 100_000):
        for endpoint in ENDPOINTS:
            out.append((endpoint, "(" * depth + "gsd > 0" + ")" * depth, None))
        out.append(("GET /stac/search", "NOT " * depth + "gsd > 0", None))
        out.append(("GET /stac/search", "gsd IN " + "(" * depth + "1" + ")" * depth, None))
        out.append(("POST /stac/search", None, b'{"filter": ' + b"[" * depth + b"]" * depth + b"}"))
        out.append(("POST /stac/search", None, b"{" + b'"a": {' * depth + b"}" * depth + b"}"))
        out.append(("POST /stac/search", None, b'{"intersects": {"type": "Polygon", "coordinates": '
                    + b"[" * depth + b"]" * depth + b"}}"))
    for digits in (310, 400, 5000):
        big = b"9" * digits
        out.append(("POST /stac/search", None, b'{"limit": ' + big + b"}"))
        out.append(("POST /stac/search", None, b'{"limit": 1e' + big[:6] + b"}"))
        out.append(("GET /stac/search", f"gsd < {'9' * digits}", None))
        out.append(("GET /stac/search", f"gsd < 1e{'9' * min(digits, 20)}", None))
    for _ in range(40):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 400)))
        endpoint = rng.choice(ENDPOINTS)
        if endpoint.startswith("POST"):
            out.append((endpoint, None, junk))
        else:
            out.append((endpoint, junk.decode("latin-1"), None))
    return out


def test_fuzz_the_live_server_survives_and_answers_400(server):
    """A bounded fuzz (~100 requests): every answer a 400 with a message; the process never dies."""
    proc, base = server
    rng = random.Random(30)
    inputs = _fuzz_inputs(rng)
    started = time.monotonic()
    for k, (endpoint, text, body) in enumerate(inputs):
        status, doc = search(base, endpoint, text, body)
        shown = (text or body or b"")[:50]
        assert proc.poll() is None, f"request {k} ({endpoint} {shown!r}) killed the server: exit {proc.returncode}"
        assert status == 400, (k, endpoint, shown, status, doc)
        assert doc.get("description") or doc.get("text"), (k, endpoint, shown, doc)
        if k % 10 == 0:
            assert_alive(proc, base)
    assert_alive(proc, base)
    assert time.monotonic() - started < 240


def test_clients_that_leave_mid_post_are_not_logged(archive_dir):
    """Issue 50: a client that disconnects in the middle of a POST body (closed, or reset) costs nothing:
    no traceback in the server's log, and the next client is answered."""
    import socket
    import struct
    from urllib.parse import urlsplit

    proc, base = start_view(archive_dir)
    try:
        where = urlsplit(base)
        for reset in (False, True, False, True):
            s = socket.create_connection((where.hostname, where.port))
            if reset:   # RST instead of FIN
                s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.sendall(b"POST /stac/search HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                      b"Content-Length: 5000\r\n\r\n{\"limit\": 1")
            time.sleep(0.3)
            s.close()
        time.sleep(0.5)
        assert_alive(proc, base)
    finally:
        stop_view(proc)
    log = proc.stderr.read()
    assert "Traceback" not in log and "Exception in ASGI" not in log, log
