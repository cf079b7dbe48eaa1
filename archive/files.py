"""Writing files and folders whole or not at all: to a temporary name beside the target, then renamed
into place.

The lowest layer of the package (imports only the error tree): raw formats, the collection store, the
output writers, the COG spool and the catalog all write through :func:`write_atomic` or
:func:`atomic_path`; outputs are moved into place (a folder replacing a folder included) by
:func:`replace_path`. :class:`FileLock` makes a job exclusive across processes and hosts (an
ingest of one collection id, a batch into one output folder).

Object storage (``s3://`` locations, :mod:`archive.storage`): one PUT is atomic, so
:func:`write_atomic` is one PUT and :func:`atomic_path` writes a local temporary then uploads it
once; :class:`FileLock` on a URL is a lock object created with a conditional PUT (``If-None-Match: *``),
its heartbeat a re-PUT by its owner, its lease read from the object's LastModified.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from archive import storage
from archive.errors import ArchiveError

__all__ = ["FileLock", "LockHeldError", "LockOwner", "atomic_path", "host_name", "path_exists", "pid_alive",
           "remove_path", "replace_path", "test_hold", "test_hold_calls", "wait_while_exists", "write_atomic"]


def wait_while_exists(path: str | os.PathLike) -> None:
    """Test hooks' wait (never reached outside tests): touch ``PATH.reached`` when ``path`` exists,
    then sleep while it exists, so that a test acts at a moment it controls and lets go by deleting it."""
    if Path(path).exists():
        Path(f"{path}.reached").touch()
    while Path(path).exists():
        time.sleep(0.05)


#: Test-only: ``ARCHIVE_TEST_KILL_AT=POINT`` makes the process SIGKILL itself when it reaches POINT (a writer's
#: name for a moment of its commit: ``after-data``, ``apply-staged``, ...; never set outside tests).
TEST_KILL_AT = "ARCHIVE_TEST_KILL_AT"


def test_kill(point: str) -> None:
    """A test hook: SIGKILL this process when :data:`TEST_KILL_AT` names ``point``."""
    if os.environ.get(TEST_KILL_AT) == point:
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def test_hold(variable: str, reached: int) -> None:
    """A test hook (the environment ``variable`` is never set outside tests): with ``N`` or ``N:PATH``
    in it and ``reached`` >= N (flights done, tile writes started...), wait: until the process is
    killed, or, with PATH, while that file exists (:func:`wait_while_exists`)."""
    hold = os.environ.get(variable)
    if hold is None:
        return
    count, _, path = hold.partition(":")
    if reached < int(count):
        return
    if not path:
        while True:
            time.sleep(3600)
    wait_while_exists(path)


_HOLD_CALLS: dict[str, int] = {}
_HOLD_LOCK = threading.Lock()


def test_hold_calls(variable: str) -> None:
    """:func:`test_hold` counting this process's calls for ``variable`` (tile writes, chunk writes
    started): the calls after its first N wait. Nothing is counted while the variable is unset."""
    if os.environ.get(variable) is None:
        return
    with _HOLD_LOCK:
        before = _HOLD_CALLS.get(variable, 0)
        _HOLD_CALLS[variable] = before + 1
    test_hold(variable, before)


def _temporary(path: str) -> str:
    """A temporary name beside ``path``, unique per call (concurrent writers of one path never share it)."""
    return f"{path}.{uuid.uuid4().hex}.partial"


def remove_path(path: str | os.PathLike) -> None:
    """Delete a file, link or directory tree (an object, or every object under a prefix); silent when absent."""
    if storage.is_url(path):
        storage.delete(path)
        storage.delete_prefix(path)
        return
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def path_exists(path: str | os.PathLike) -> bool:
    """True when ``path`` exists (a dangling link counts; for a URL: an object or a prefix)."""
    if storage.is_url(path):
        return storage.exists(path) or next(storage.list_names(path), None) is not None
    path = Path(path)
    return path.exists() or path.is_symlink()


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write (a file, by any writer: zip, numpy, text); renamed
    over ``path`` when the block completes. On any error the temporary is removed and ``path`` is
    left as it was. Nested blocks rename innermost first (write a data file inside its header's
    block: the header lands last). For a URL: a local temporary, uploaded in one PUT at the end."""
    if storage.is_url(path):
        import tempfile

        fd, tmp = tempfile.mkstemp(suffix=".partial", prefix="archive-upload-")
        os.close(fd)
        try:
            yield Path(tmp)
            with open(tmp, "rb") as f:
                storage.write_bytes(path, f.read())
        finally:
            remove_path(tmp)
        return
    path = os.fspath(path)
    tmp = _temporary(path)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        remove_path(tmp)
        raise


def write_atomic(path: str | os.PathLike, parts: Iterable[bytes | memoryview] | bytes | str) -> None:
    """Write ``parts`` (bytes-like objects, or one; a str is written as UTF-8) to ``path`` through
    :func:`atomic_path`."""
    if isinstance(parts, str):
        parts = parts.encode("utf-8")
    if storage.is_url(path):   # one PUT: atomic by itself
        storage.write_bytes(path, parts if isinstance(parts, (bytes, bytearray, memoryview)) else b"".join(parts))
        return
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        if isinstance(parts, (bytes, bytearray, memoryview)):
            f.write(parts)
        else:
            f.writelines(parts)


def replace_path(tmp: str | os.PathLike, final: str | os.PathLike) -> None:
    """Rename ``tmp`` (a file or a folder) to ``final``; an existing ``final`` (a folder too) is moved
    aside first and deleted only once ``tmp`` is in place (put back if the rename fails)."""
    tmp, final = Path(tmp), Path(final)
    old = None
    if path_exists(final):
        old = final.with_name(f".{final.name}.old-{os.getpid()}@{host_name()}")
        remove_path(old)
        os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        raise
    if old is not None:
        remove_path(old)


# ----------------------------------------------------------------------------------------------
# exclusive locks across processes and hosts

#: Seconds a lock held by a process of another host stays valid without a heartbeat (its owner
#: touches the lock file every :data:`LOCK_HEARTBEAT_SECONDS`); after that it is taken over.
LOCK_LEASE_SECONDS = 120.0
#: Seconds between two heartbeats of a held lock (its file's mtime is renewed).
LOCK_HEARTBEAT_SECONDS = 10.0


def host_name() -> str:
    """This machine's name as recorded in lock files and temporaries' names ('.' -> '_': a
    temporary's name may carry a suffix after it)."""
    return (socket.gethostname() or "localhost").replace(".", "_").replace("/", "_") or "localhost"


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` on this host (clock ticks since boot, /proc/PID/stat field 22),
    which tells a live owner from another process that got its PID later; None where unknown."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2:].split()
    return fields[19] if len(fields) > 19 else None


def pid_alive(pid: int, start: str | None = None) -> bool:
    """Whether process ``pid`` runs on THIS host (and, when ``start`` is given and known, is the
    process that started then, not a later one that reused its PID)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # exists, owned by someone else
        pass
    if start is not None:
        now = _process_start(pid)
        if now is not None and now != start:
            return False
    return True


@dataclass(frozen=True)
class LockOwner:
    """Who holds a lock: host (:func:`host_name`), PID, process start (see :func:`pid_alive`), when
    it was taken (UTC, ISO 8601) and what for."""

    host: str
    pid: int
    process_start: str | None
    since: str
    purpose: str

    def describe(self) -> str:
        """'<purpose> by PID <pid> on <host> since <time>'."""
        return f"{self.purpose} by PID {self.pid} on {self.host} since {self.since}"


class LockHeldError(ArchiveError):
    """An exclusive lock (:class:`FileLock`) is held by another live process."""

    def __init__(self, path: str | os.PathLike, owner: LockOwner | None, what: str, fix: str):
        self.path, self.owner = str(path), owner
        who = owner.describe() if owner is not None else "by another process (its lock file is being written)"
        super().__init__(f"{what} is locked: {who} (lock file {self.path}; {fix})")


class FileLock:
    """An exclusive lock between processes and hosts sharing a file system: the lock file
    ``path`` is created atomically (a complete temporary hard-linked to ``path``, which fails when
    it exists; ``O_EXCL`` where links are not supported) and holds its owner (:class:`LockOwner`,
    JSON). While held, a thread renews the file's mtime every ``heartbeat`` s.

    A lock is taken over only when its owner is dead for sure: on THIS host, when its PID no
    longer runs (or runs another process); from another host, only when its lease ran out (no
    heartbeat for ``lease`` s). The take-over itself is exclusive (``<path>.break``), so that two
    waiters never both break it and the second never deletes the first's new lock.

    Use as a context manager, or :meth:`acquire` / :meth:`release`.
    """

    def __init__(self, path: str | os.PathLike, purpose: str, *, what: str | None = None,
                 fix: str = "wait for it to finish", lease: float = LOCK_LEASE_SECONDS,
                 heartbeat: float = LOCK_HEARTBEAT_SECONDS):
        self.url = storage.is_url(path)
        self.path = storage.location(path) if self.url else Path(path)
        self.purpose, self.what, self.fix = purpose, what or str(self.path), fix
        self.lease, self.heartbeat = float(lease), float(heartbeat)
        self._stop: threading.Event | None = None
        self._thread: threading.Thread | None = None
        self._mine: bytes | None = None

    # -- reading --------------------------------------------------------------------------------
    def owner(self) -> tuple[LockOwner | None, bytes | None, float | None]:
        """(owner, the file's bytes, its mtime) of the current lock file; (None, None, None) when there
        is none, (None, bytes, mtime) when it cannot be read as an owner."""
        if self.url:   # the object's bytes and its LastModified (the server's clock)
            meta = storage.head(self.path)
            try:
                raw = storage.read_bytes(self.path) if meta is not None else None
            except FileNotFoundError:
                raw = None
            if raw is None:
                return None, None, None
            return self._parse(raw), raw, meta["last_modified"].timestamp()
        try:
            with open(self.path, "rb") as f:
                raw = f.read()
                mtime = os.fstat(f.fileno()).st_mtime
        except FileNotFoundError:
            return None, None, None
        except OSError:
            return None, b"", time.time()
        return self._parse(raw), raw, mtime

    @staticmethod
    def _parse(raw: bytes) -> LockOwner | None:
        try:
            d = json.loads(raw)
            owner = LockOwner(str(d["host"]), int(d["pid"]), d.get("process_start"), str(d["since"]),
                              str(d.get("purpose", "")))
        except (ValueError, KeyError, TypeError):
            owner = None
        return owner

    def _alive(self, owner: LockOwner | None, mtime: float) -> bool:
        if owner is not None and owner.host == host_name():
            return pid_alive(owner.pid, owner.process_start)
        # another host's owner (or an unreadable file): alive while its lease runs
        return time.time() - mtime < self.lease

    # -- taking and giving back -------------------------------------------------------------------
    def _create(self) -> bool:
        me = LockOwner(host_name(), os.getpid(), _process_start(os.getpid()),
                       datetime.now(UTC).isoformat(timespec="seconds"), self.purpose)
        raw = (json.dumps(dataclasses.asdict(me)) + "\n").encode()
        if self.url:   # conditional PUT: exactly one of two racing creators succeeds
            if not storage.put_if_absent(self.path, raw):
                return False
            self._mine = raw
            return True
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(_temporary(os.fspath(self.path)))
        try:
            with open(tmp, "wb") as f:
                f.write(raw)
                f.flush()
                os.fsync(f.fileno())
            try:
                os.link(tmp, self.path)
            except FileExistsError:
                return False
            except OSError:   # no hard links here: O_EXCL (a reader may see it empty for a moment)
                try:
                    fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
                except FileExistsError:
                    return False
                with os.fdopen(fd, "wb") as f:
                    f.write(raw)
        finally:
            remove_path(tmp)
        self._mine = raw
        return True

    def _break(self, seen: bytes | None) -> None:
        """Remove the lock file if it still holds ``seen`` (a dead owner's), exclusively."""
        if self.url:   # the breaker is itself a lock object (conditional PUT); stale after 60 s
            breaker = storage.location(str(self.path) + ".break")
            meta = storage.head(breaker)
            if meta is not None and time.time() - meta["last_modified"].timestamp() > 60:
                storage.delete(breaker)
            if not storage.put_if_absent(breaker, b"break"):
                return
            try:
                _, now, _ = self.owner()
                if now == seen:
                    storage.delete(self.path)
            finally:
                storage.delete(breaker)
            return
        breaker = self.path.with_name(self.path.name + ".break")
        try:
            if time.time() - breaker.stat().st_mtime > 60:   # a breaker killed while breaking
                remove_path(breaker)
        except OSError:
            pass
        try:
            fd = os.open(breaker, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return
        os.close(fd)
        try:
            _, now, _ = self.owner()
            if now == seen:
                remove_path(self.path)
        finally:
            remove_path(breaker)

    def try_acquire(self) -> LockOwner | None:
        """Take the lock if it is free (or its owner is dead: see the class); None when taken,
        else the live owner that holds it."""
        for _ in range(100):
            if self._create():
                self._start_heartbeat()
                return None
            owner, raw, mtime = self.owner()
            if raw is None:
                continue   # released meanwhile
            if self._alive(owner, mtime):
                return owner or LockOwner("?", 0, None, "?", "an unreadable lock file")
            self._break(raw)
        raise OSError(f"{self.path}: cannot take the lock")   # pathological contention

    def acquire(self, wait: float = 0.0, notify: Callable[[str], None] | None = None,
                poll: float = 0.2) -> None:
        """Take the lock, waiting up to ``wait`` s (``math.inf``: as long as its live owner holds it)
        for another owner to give it back; ``notify(line)`` is told once that this process waits.
        :class:`LockHeldError` (naming the owner) when it is still held then."""
        deadline = time.monotonic() + wait
        told = False
        while True:
            owner = self.try_acquire()
            if owner is None:
                return
            if time.monotonic() >= deadline:
                raise LockHeldError(self.path, owner, self.what, self.fix)
            if not told and notify is not None:
                notify(f"waiting: {self.what} is locked, {owner.describe()}")
                told = True
            time.sleep(min(poll, max(deadline - time.monotonic(), 0.0)))

    def _start_heartbeat(self) -> None:
        self._stop = threading.Event()

        def beat(stop: threading.Event = self._stop) -> None:
            while not stop.wait(self.heartbeat):
                try:
                    if self.url:   # re-PUT the same bytes (new LastModified) while it is still ours
                        _, raw, _ = self.owner()
                        if raw == self._mine and raw is not None:
                            storage.write_bytes(self.path, raw)
                    else:
                        os.utime(self.path)
                except OSError:
                    pass

        self._thread = threading.Thread(target=beat, name=f"lock-heartbeat {self.path.name}", daemon=True)
        self._thread.start()

    def release(self) -> None:
        """Give the lock back (its file removed if it is still this process's)."""
        if self._stop is not None:
            self._stop.set()
            self._stop = None
        if self._mine is not None:
            _, raw, _ = self.owner()
            if raw == self._mine:
                if self.url:
                    storage.delete(self.path)
                else:
                    remove_path(self.path)
            self._mine = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._mine is not None

    def __enter__(self) -> FileLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
