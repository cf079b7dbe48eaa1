"""``archive watch``: follow recorder folders, list each complete cube on the live map, ingest each
flight once it has been idle (docs/watch.md).

The main thread runs the loop: scan the folders (:class:`archive.watch.follow.Follower`) when inotify
says something changed (``watchfiles``, in a thread) or a timer expires (a cube settling or stalling,
a flight going idle; every ``--poll`` seconds on network mounts), then act on what the scan found:

- a complete cube is staged (:mod:`archive.watch.stage`) and served at once as a raw flight of its own
  (:class:`archive.watch.live.LiveRegistry`), listed in ``/api/live``; then its DN chunks are encoded
  ahead of the ingest, in a thread, one cube at a time (:mod:`archive.watch.ahead`);
- a flight idle for ``--idle`` seconds (no cube of it being written or encoded) is ingested by
  ``archive ingest --prewritten`` (the chunks encoded ahead) with the options given, in a child process
  (one at a time): its collection is exactly what a plain ingest of its files makes, because it is one
  (the ingest moves in only the chunks that are exactly its own, and writes the rest). The recorder folder itself is ingested when it holds
  exactly that flight's complete cubes, else a staged folder of links to them. Once the collection is
  in the catalog, the flight's live cubes leave the list;
- what was ingested is recorded in ``ARCHIVE/.watch/state.json`` (the cubes' sizes and times), so a
  watch restarted on the same folders lists and ingests nothing again; a flight that grew since is
  ingested again (``--overwrite`` of the collection this watcher made).

SIGTERM or Ctrl-C stops the loop: the cube in hand is finished (staging is a rename; the cube being
encoded ahead is finished, the cubes queued behind it are dropped: the ingest writes them), an ingest in
progress is stopped (its partial store stays, invisible to readers, and the next watch resumes it);
exit 0. Faults that cost only themselves (a cube that never completes, a folder that disappears, a
recorder writing over a cube, an ingest refusing a flight) are one line each and the watch goes on.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from archive.errors import InputError
from archive.files import remove_path, write_atomic
from archive.watch.ahead import Encoder, place
from archive.watch.arguments import ingest_argv
from archive.watch.follow import Changed, Complete, CubeState, FolderBack, FolderGone, Follower, Skipped, flight_name
from archive.watch.live import LiveRegistry, LiveState, live_routes
from archive.watch.stage import flight_extras, safe_name, stage_links

__all__ = ["NETWORK_FILE_SYSTEMS", "Watch", "network_mount", "run"]

#: File system types that send no inotify events for changes made by other hosts: polled.
NETWORK_FILE_SYSTEMS = ("nfs", "nfs4", "cifs", "smb3", "smbfs", "fuse.sshfs", "9p", "afs", "fuse.rclone",
                        "fuse.s3fs", "ceph", "glusterfs", "lustre", "davfs", "fuse.davfs2", "gcsfuse", "fuse.gcsfuse")


def network_mount(path: Path) -> str | None:
    """The type of the network file system holding ``path`` (its longest mount point in /proc/self/mounts),
    None for a local one (or where /proc is not there)."""
    try:
        rows = [line.split() for line in Path("/proc/self/mounts").read_text().splitlines()]
    except OSError:
        return None
    target = os.path.realpath(path)
    best, kind = "", None
    for row in rows:
        if len(row) < 3:
            continue
        point = row[1].replace("\\040", " ")
        if (target == point or target.startswith(point.rstrip("/") + "/")) and len(point) >= len(best):
            best, kind = point, row[2]
    return kind if kind in NETWORK_FILE_SYSTEMS else None


@dataclass
class _Flight:
    key: tuple
    name: str
    live: dict[str, str] = field(default_factory=dict)     #: cube base -> the viewer id of its staged cube
    updated: float = 0.0                                   #: when a cube of it last completed (s)
    collection: str | None = None
    ingested: list | None = None                           #: the cubes (base, signature) it was ingested with
    failed: list | None = None                             #: the cubes an ingest refused (not tried again)
    staged: dict[str, int] = field(default_factory=dict)   #: stagings of each cube (one written over: a new folder)
    behind: bool = False                                   #: said that the encoding falls behind


class Watch:
    """One ``archive watch`` (see the module docstring). ``ingest_options``: ``archive ingest`` words;
    ``say(line)`` prints one line; ``registry``: where live cubes are served (None with --no-view)."""

    def __init__(self, folders: list[Path], archive: Path, fov: float, ingest_options: list[str], *,
                 idle: float = 30.0, settle: float = 0.5, stall: float = 15.0, registry: LiveRegistry | None = None,
                 state: LiveState | None = None, say=print, quiet: bool = False, ahead: bool = True):
        self.follower = Follower([Path(f).absolute() for f in folders], settle=settle, stall=stall)
        self.archive, self.fov, self.options = Path(archive).absolute(), float(fov), list(ingest_options)
        self.idle = idle
        self.registry, self.state = registry, state or LiveState()
        self.say, self.quiet = say, quiet
        self.work = self.archive / ".watch"
        self.flights: dict[tuple, _Flight] = {}
        self.ingesting: tuple[_Flight, list, subprocess.Popen, float] | None = None
        self.record = self._read_record()
        self.encoder = None
        if ahead and not any(o.startswith("--workers=") and o.split("=", 1)[1].strip() not in ("", "1")
                             for o in self.options):   # an ingest on a cluster writes every chunk itself
            from archive.ingest.flight import store_choices

            self.encoder = Encoder(self.work, *store_choices(None, None))

    # ---- the record of what was ingested ---------------------------------------------------------------
    def _read_record(self) -> dict:
        path = self.work / "state.json"
        try:
            return json.loads(path.read_text()).get("flights", {})
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            self.say(f"archive watch: {path}: unreadable ({exc}); starting afresh (ingest itself skips what is in)")
            return {}

    def _write_record(self) -> None:
        self.work.mkdir(parents=True, exist_ok=True)
        write_atomic(self.work / "state.json", json.dumps({"flights": self.record}, indent=1))

    def _flight(self, key: tuple) -> _Flight:
        found = self.flights.get(key)
        if found is None:
            found = self.flights[key] = _Flight(key, flight_name(key))
            done = self.record.get(found.name)
            if done and done.get("folder") == str(key[0]):
                found.collection, found.ingested = done.get("collection"), [tuple(map(_tuple, c)) for c in done["cubes"]]
            self.state.flight(found.name, folder=str(key[0]), image_set=key[1])
            others = [f for f in self.flights.values() if f.key[0] == key[0] and f is not found]
            if others:
                self.say(f"archive watch: {found.name}: a new image set: a new flight (after {others[-1].name})")
        return found

    # ---- one scan's events ---------------------------------------------------------------------------
    def step(self, now: float) -> None:
        """Scan once, act on what changed, start or finish an ingest."""
        for event in self.follower.scan(now):
            try:
                self._act(event, now)
            except Exception as exc:   # a bug or a file system surprise costs this event, not the watch
                self.say(f"archive watch: {type(event).__name__.lower()} event not handled "
                         f"({type(exc).__name__}: {' '.join(str(exc).split())[:300]}); going on")
        self._encoded()
        self._finish_ingest(now)
        self._retire_live()
        if self.ingesting is None:
            self._start_ingest(now)

    def _act(self, event, now: float) -> None:
        """Act on one event of a scan (see the module docstring)."""
        if isinstance(event, Complete):
            self._complete(event.cube, now)
        elif isinstance(event, Skipped):
            flight = self._flight(event.cube.flight)
            self.say(f"archive watch: {flight.name}: cube {event.cube.base} skipped: {event.why}")
            self.state.skipped(flight.name, event.cube.base)
        elif isinstance(event, Changed):
            flight = self._flight(event.cube.flight)
            self.say(f"archive watch: {flight.name}: cube {event.cube.base}: {event.why}")
            self._unlist(flight, [event.cube.base])
        elif isinstance(event, FolderGone):
            self.say(f"archive watch: {event.folder}: the folder is gone (unplugged, unmounted?); its "
                     f"{len(event.cubes)} complete cubes are no longer shown; watching for it to come back")
            for flight in [f for f in self.flights.values() if f.key[0] == event.folder]:
                self._unlist(flight, list(flight.live))
                self.state.flight(flight.name, status="gone")
        elif isinstance(event, FolderBack):
            self.say(f"archive watch: {event.folder}: the folder is back; looking at its cubes again")

    def _complete(self, cube: CubeState, now: float) -> None:
        flight = self._flight(cube.flight)
        if flight.ingested is not None and (cube.base, cube.sig) in flight.ingested:
            self.state.flight(flight.name, status="ingested", complete=True, collection=flight.collection)
            return   # in the collection already (a restarted watch)
        times = flight.staged[cube.base] = flight.staged.get(cube.base, 0) + 1
        name = cube.base if times == 1 else f"{cube.base}.{times}"
        target = self.work / "cubes" / safe_name(flight.name) / safe_name(name)
        try:
            stage_links(target, [cube.data], flight_extras(cube.data.parent, [c.base for c in self.follower.cubes.values()
                                                                              if c.data.parent == cube.data.parent]))
            feature = self.registry.add_cube(target) if self.registry is not None else None
        except Exception as exc:   # the raw reader refuses it (navigation not covering its lines...): costs this cube
            cube.state, cube.reported = "skipped", True
            remove_path(target)
            self.say(f"archive watch: {flight.name}: cube {cube.base} skipped: {' '.join(str(exc).split())[:300]}")
            self.state.skipped(flight.name, cube.base)
            return
        flight.updated = now
        if feature is not None:
            flight.live[cube.base] = feature["id"]
            self.state.add_cube(flight.name, feature)
        self.state.flight(flight.name, status="recording", complete=False)
        self._encode(flight, cube)
        if not self.quiet:
            listed = len(flight.live) if self.registry is not None else sum(
                1 for c in self.follower.cubes.values() if c.flight == flight.key and c.state == "complete")
            self.say(f"archive watch: {flight.name}: cube {cube.base} complete ({cube.check.lines} lines), "
                     f"{listed} listed")

    def _encode(self, flight: _Flight, cube: CubeState) -> None:
        """Queue ``cube``'s DN chunks to be encoded ahead of the ingest, where the layout guessed from
        the flight's cubes so far gives it one line chunk."""
        if self.encoder is None or cube.check is None:
            return
        where = place([(c.base, c.check.lines) for c in self._complete_cubes(flight) if c.check is not None],
                      cube.base)
        if where is not None and self.encoder.submit(flight.name, cube.data, cube.base, where):
            if self.encoder.waiting() > 2 and not flight.behind:
                flight.behind = True
                self.say(f"archive watch: {flight.name}: falls behind: {self.encoder.waiting()} cubes wait to be "
                         "encoded (the collection will come later after landing)")

    def _encoded(self) -> None:
        """Record the cubes encoded since the last scan; one line for one that could not be."""
        if self.encoder is None:
            return
        for name, base, record, error in self.encoder.poll():
            if error is not None:
                self.say(f"archive watch: {name}: cube {base} not encoded ahead ({type(error).__name__}: "
                         f"{' '.join(str(error).split())[:200]}); the ingest will write it")
            else:
                flight = next((f for f in self.flights.values() if f.name == name), None)
                if flight is not None:
                    self.state.flight(name, encoded=len(self.encoder.seconds.get(name, [])))

    def _unlist(self, flight: _Flight, bases: list[str]) -> None:
        ids = [flight.live.pop(b) for b in bases if b in flight.live]
        if ids:
            if self.registry is not None:
                self.registry.remove(ids)
            self.state.drop_cubes(flight.name, ids)

    def _retire_live(self) -> None:
        """Live cubes of ingested flights leave the list once the collection is in the catalog."""
        if self.registry is None:
            return
        done = [f for f in self.flights.values() if f.live and f.collection and f.ingested is not None
                and all((c.base, c.sig) in f.ingested for c in self._complete_cubes(f))]
        if done and any(f.collection in self.registry.catalog_ids() for f in done):
            ids = self.registry.catalog_ids()
            for f in done:
                if f.collection in ids:
                    self._unlist(f, list(f.live))
                    # its staged cubes are no longer served: their folders of links go (a cube written
                    # over later is staged again under a new name)
                    remove_path(self.work / "cubes" / safe_name(f.name))

    def _complete_cubes(self, flight: _Flight) -> list[CubeState]:
        return [c for c in self.follower.flights().get(flight.key, []) if c.state == "complete"]

    # ---- ingest --------------------------------------------------------------------------------------
    def _ready(self, flight: _Flight, now: float) -> list | None:
        """The cubes (base, signature) to ingest ``flight`` with now, None when it is not due."""
        cubes = self.follower.flights().get(flight.key, [])
        if not cubes or any(c.state == "growing" for c in cubes) or now - flight.updated < self.idle:
            return None
        if self.encoder is not None and self.encoder.busy(flight.name):
            return None
        done = sorted((c.base, c.sig) for c in cubes if c.state == "complete")
        if not done or done == sorted(flight.ingested or []) or done == flight.failed:
            return None
        return done

    def _start_ingest(self, now: float) -> None:
        for flight in self.flights.values():
            cubes = self._ready(flight, now)
            if cubes is None:
                continue
            folder = Path(flight.key[0])
            everything = [c for c in self.follower.cubes.values() if c.data.parent == folder]
            if all(c.flight == flight.key and c.state == "complete" for c in everything):
                directory = folder   # the recorder folder is exactly this flight: a plain ingest of it
            else:
                directory = stage_links(self.work / "flights" / safe_name(flight.name),
                                        [c.data for c in everything if c.flight == flight.key and c.state == "complete"],
                                        flight_extras(folder, [c.base for c in everything]))
            overwrite = ["--overwrite"] if flight.ingested is not None else []
            ahead = self.encoder.folder(flight.name) if self.encoder is not None else None
            prewritten = ["--prewritten", str(ahead)] if ahead is not None and ahead.is_dir() else []
            argv = [sys.executable, "-m", "archive", "ingest", str(directory), "--archive", str(self.archive),
                    "--fov", repr(self.fov), "--quiet", *self.options, *prewritten, *overwrite]
            self.say(f"archive watch: {flight.name}: idle {self.idle:g} s with {len(cubes)} cubes: ingesting")
            self.state.flight(flight.name, status="ingesting")
            proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
            self.ingesting = (flight, cubes, proc, time.monotonic())
            return

    def _finish_ingest(self, now: float) -> None:
        if self.ingesting is None or self.ingesting[2].poll() is None:
            return
        flight, cubes, proc, started = self.ingesting
        self.ingesting = None
        out, err = proc.communicate()
        seconds = time.monotonic() - started
        if proc.returncode != 0:
            last = [line for line in err.splitlines() if line.strip()][-1:] or [f"exit code {proc.returncode}"]
            flight.failed = cubes
            self.state.flight(flight.name, status="failed", error=last[0])
            self.say(f"archive watch: {flight.name}: not ingested: {last[0]}")
            return
        cid = out.split(":", 1)[0].strip() if out.strip() else None
        flight.collection, flight.ingested, flight.failed = cid, cubes, None
        remove_path(self.work / "flights" / safe_name(flight.name))   # the staged folder ingested, if one was
        pace = self._pace(flight, len(cubes), seconds)
        if self.encoder is not None:   # what the ingest did not move in is of no use any more
            self.encoder.discard(flight.name)
        self.record[flight.name] = {"folder": str(flight.key[0]), "collection": cid,
                                    "cubes": [[b, list(map(_listed, s))] for b, s in cubes]}
        self._write_record()
        still = self._ready(flight, now) is None and all(c.state != "growing" for c in self._complete_cubes(flight))
        self.state.flight(flight.name, status="ingested", collection=cid, complete=still, ingest_seconds=round(seconds, 3))
        self.say(f"archive watch: {flight.name}: ingested as {cid} in {seconds:.1f} s ({len(cubes)} cubes; {pace})")

    def _pace(self, flight: _Flight, cubes: int, seconds: float) -> str:
        """Whether the ingest keeps pace with the recorder: its seconds a cube against the seconds the
        recorder took to record one (the cubes' ``.times``: last line - first line + one interval)."""
        from archive.formats.times import read_times
        from archive.watch.cubes import cube_files

        spans = []
        for c in self._complete_cubes(flight):
            try:
                t = read_times(cube_files(c.data)[2])
            except Exception:   # (gone since): the others tell
                continue
            if len(t) > 1:
                spans.append(float(t[-1] - t[0]) * len(t) / (len(t) - 1))
        encoded = self.encoder.seconds.get(flight.name, []) if self.encoder is not None else []
        if encoded:   # the work done as the cubes closed; the ingest's seconds came after the last
            per = sum(encoded) / len(encoded)
            moved, _ = self.encoder.moved(flight.name)
            head = f"{len(encoded)} encoded as they closed, {moved} moved in, {per:.1f} s a cube"
        else:
            per, head = seconds / cubes, f"{seconds / cubes:.1f} s a cube"
        if not spans:
            return head
        record = sum(spans) / len(spans)
        if per <= record:
            return f"{head}, the recorder takes {record:.1f} s: keeps pace"
        return (f"{head}, the recorder takes {record:.1f} s: falls behind by {per - record:.1f} s a cube "
                f"({(per - record) * cubes:.0f} s over this flight)")

    def stop(self) -> None:
        """Stop an ingest in progress (its partial store stays for the next run to resume) and the
        encoding ahead (the cube in hand finished, those queued dropped)."""
        if self.encoder is not None:
            self.encoder.stop()
        if self.ingesting is not None:
            flight, _, proc, _ = self.ingesting
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            self.say(f"archive watch: {flight.name}: ingest stopped; the next watch resumes it")
            self.ingesting = None

    def next_wait(self, now: float) -> float:
        """Seconds until the next scan is due without an inotify event."""
        due = [1.0]
        for c in self.follower.cubes.values():
            if c.state == "growing":
                due += [c.changed + self.follower.settle - now, c.changed + self.follower.stall - now]
        if self.ingesting is not None or (self.encoder is not None and self.encoder.waiting()):
            due.append(0.2)
        return max(0.05, min(d for d in due if d > -1.0) if due else 1.0)


def _listed(v):
    return None if v is None else list(v)


def _tuple(v):
    return tuple(_tuple(x) for x in v) if isinstance(v, list) else v


# ---- the command -----------------------------------------------------------------------------------
def _notify(folders: list[Path], wake: threading.Event, stop: threading.Event) -> None:
    """Set ``wake`` whenever inotify reports a change in a folder (``watchfiles``); re-armed when a
    folder appears or disappears (checked every second)."""
    import watchfiles

    while not stop.is_set():
        present = [str(f) for f in folders if f.is_dir()]
        if not present:
            stop.wait(1.0)
            continue
        try:
            for changes in watchfiles.watch(*present, stop_event=stop, debounce=30, step=10, rust_timeout=1000,
                                            yield_on_timeout=True, recursive=False, raise_interrupt=False,
                                            ignore_permission_denied=True):
                if changes:
                    wake.set()
                if [str(f) for f in folders if f.is_dir()] != present:
                    wake.set()
                    break
        except Exception:   # a watched folder vanished under inotify: look again in a second
            wake.set()
            stop.wait(1.0)


def run(args: argparse.Namespace) -> int:
    """The ``archive watch`` command."""
    from archive.catalog.root import create_archive
    from archive.storage import is_url

    if is_url(args.archive):
        raise InputError("--archive", f"{args.archive}: archive watch writes into a local archive (its staged cubes "
                         "live beside the collections)", "watch into a local archive; sync it to object storage after")
    if not (0 < args.fov < 180):
        raise InputError("--fov", f"field of view {args.fov} deg is not in (0, 180)", "47.5 for a Pika L")
    for name in ("calibration", "irradiance_calibration", "dem", "navigation"):
        value = getattr(args, name, None)
        if value is not None and not Path(value).is_file():
            raise InputError(f"--{name.replace('_', '-')}", f"{value}: no such file", "name an existing file")
    if args.cache_mb <= 0:
        raise InputError("--cache-mb", f"must be a positive number of MiB, got {args.cache_mb}")
    folders = [Path(f).absolute() for f in args.folders]
    create_archive(args.archive)
    say = _say
    for f in folders:
        if not f.is_dir():
            say(f"archive watch: {f}: not there yet; watching for it")
    polled = {f: network_mount(f) for f in folders}
    polling = args.poll is not None or any(polled.values())
    for f, kind in polled.items():
        if kind and args.poll is None:
            say(f"archive watch: {f} is on {kind} (no inotify events from other hosts): polling every 1 s")
    registry = None
    state = LiveState()
    server_box: dict = {}
    thread = None
    if not args.no_view:
        from archive.view.server import cache_bytes, serve
        from archive.drawing.cache import ByteLRU

        limits = cache_bytes(args.cache_mb)
        registry = LiveRegistry(args.archive, args.fov, _flat_ground(args.ground_height), bands_cache=ByteLRU(limits["bands"]),
                                lookup_cache=ByteLRU(limits["lookups"]), flights_cache=ByteLRU(limits["flights"]))

        listening, failed = threading.Event(), []

        def announce(url: str) -> None:
            say(f"archive watch: live map at {url}  (Ctrl-C stops)")
            listening.set()

        def serve_thread():
            try:
                serve(registry, args.host, args.port, allow_remote=args.allow_remote, cache_mb=args.cache_mb,
                      announce=announce, ready=lambda s: server_box.setdefault("server", s),
                      extra_routes=live_routes(state))
            except Exception as exc:   # before listening: the command's one line (a port in use); after: one line
                failed.append(exc)
                if listening.is_set():
                    say(f"archive watch: the live map stopped: {' '.join(str(exc).split())}")
            finally:
                listening.set()
        thread = threading.Thread(target=serve_thread, name="archive-watch-view", daemon=True)
        thread.start()
        listening.wait()
        if failed:
            raise failed[0]
    watch = Watch(folders, Path(args.archive), args.fov, ingest_argv(args), idle=args.idle, settle=args.settle,
                  stall=args.stall, registry=registry, state=state, say=say, quiet=args.quiet)
    stop, wake = threading.Event(), threading.Event()

    def on_signal(signum, frame):
        stop.set()
        wake.set()
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    notifier = None
    if not polling:
        notifier = threading.Thread(target=_notify, args=(folders, wake, stop), name="archive-watch-inotify",
                                    daemon=True)
        notifier.start()
    say(f"archive watch: following {len(folders)} folder{'s' if len(folders) != 1 else ''} "
        f"({'polling every %g s' % (args.poll or 1.0) if polling else 'inotify'}); idle {args.idle:g} s ends a flight")
    try:
        while not stop.is_set():
            watch.step(time.time())
            wait = watch.next_wait(time.time())
            if polling and not watch.follower.growing():
                wait = args.poll or 1.0
            wake.wait(wait)
            wake.clear()
    finally:
        watch.stop()
        for s, handler in previous.items():
            signal.signal(s, handler)
        if "server" in server_box:
            server_box["server"].should_exit = True
        if thread is not None:
            thread.join(timeout=10)
        if registry is not None and thread is not None and thread.is_alive():
            registry.close()
    say("archive watch: stopped")
    return 0


def _say(line: str) -> None:
    print(line, flush=True)


def _flat_ground(value) -> float | None:
    """The live cubes' flat ground height from ``--ground-height`` (metres; None for auto or none:
    each cube's header); a value the ingest would refuse is the ingest's to name."""
    try:
        return None if value in (None, "auto") else float(value)
    except ValueError:
        return None
