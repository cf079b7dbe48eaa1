"""Publishing an output: written under temporary names, renamed into place when complete.

Nothing is ever half-written at the requested path: :class:`Output` creates the format's sinks
(:mod:`archive.outputs.registry`) under hidden temporary siblings (``.<name>.partial-<pid>@<host>...``),
renames them into place only when complete (:func:`archive.files.replace_path`: an existing output
is replaced only once the new one is complete, and only with ``overwrite``), and removes them on
failure. Temporaries a killed run left are removed by the next run's check: only those made on
THIS host whose process is gone (another host's PID means nothing here: its temporaries stay).

Replacing an output: its old STAC Item (``<out>.json``, which says the output is complete) is
removed BEFORE the new data is renamed into place, and the pipeline writes the new Item last, so a
kill at any moment leaves either the old output with its Item, or data without an Item (rendered
again by ``--resume``), never new data beside the old Item. Two processes publishing the same
output take turns (a lock, ``.<name>.publish.lock``, from :meth:`Output.finalize` until
:meth:`Output.cleanup`, so the Item written after the rename is part of the turn).

An output at an ``s3://`` URL (:class:`RemoteOutput`) is assembled by the same :class:`Output`
in a local staging folder, then uploaded once: its old Item deleted first, its old objects next,
then every file of the new output (a Zarr store's metadata files last, the data files in
parallel), then its Item, last (S3 has no rename: the Item is what publishes it). A Zarr output's
value chunks are not staged: the tile tasks PUT them straight into the bucket (its old Item and
objects are deleted before the render starts), the staging folder holds only its metadata and
small arrays, uploaded after the render.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass, field
from pathlib import Path

from archive import storage
from archive.errors import InputError, OutputExistsError
from archive.files import FileLock, host_name, path_exists, pid_alive, remove_path, replace_path, test_kill
from archive.outputs.base import OutputMeta
from archive.outputs.quicklook import quicklook_png
from archive.outputs.registry import output_format

__all__ = ["Output", "RemoteOutput", "unwritable_output"]


def _temp_owner(rest: str) -> tuple[int | None, str | None]:
    """(PID, host) from the part of a temporary's name after ``.partial-``: ``<pid>@<host>[tag]``
    (host None: a name from before hosts were recorded, ``<pid>[tag]``)."""
    digits = ""
    for ch in rest:
        if not ch.isdigit():
            break
        digits += ch
    if not digits:
        return None, None
    rest = rest[len(digits):]
    if not rest.startswith("@"):
        return int(digits), None
    return int(digits), rest[1:].split(".", 1)[0]


def _remove_stale_temps(final: Path) -> None:
    """Remove ``.<name>.partial-<pid>@<host>...`` siblings of ``final`` made on THIS host by a process
    that is gone. Another host's are left alone: its PIDs mean nothing here, and on a shared file
    system its render may be writing them right now."""
    if not final.parent.is_dir():
        return
    prefix = f".{final.name}.partial-"
    here = host_name()
    for tmp in final.parent.glob(f"{prefix}*"):
        pid, host = _temp_owner(tmp.name[len(prefix):])
        if pid is None or (host is not None and host != here):
            continue
        if pid != os.getpid() and not pid_alive(pid):
            remove_path(tmp)


@dataclass
class Output:
    """One requested output (plus an optional quicklook) and the temporary files that build it.

    Use: ``out.check()`` early; ``sink = out.sink(meta)`` creates the format's sink under temporary
    names (its format's, :mod:`archive.outputs.registry`); write every tile through it (the render
    graph's tasks do); then ``out.finalize()``; always ``out.cleanup()`` in a ``finally`` (it removes
    temporaries only). The STAC Item at :attr:`item_path` is the pipeline's to write, last.
    """

    path: Path
    overwrite: bool = False
    quicklook: Path | None = None
    provenance: bool = False   #: provenance layers: sibling file (COG, ENVI) or store variables (Zarr)
    zarr_format: int = 2   #: Zarr version of a .zarr output (2: GDAL >= 3.10 opens it; 3)
    compression: str = "fast"   #: :data:`archive.codecs.COMPRESSIONS` name of a .zarr or .tif output
    #: s3:// URL the data chunks go to straight from the tile tasks (a Zarr output in a bucket,
    #: :class:`RemoteOutput`); the local store then holds only the metadata and small arrays
    remote: str | None = None
    _temps: list[Path] = field(default_factory=list, repr=False)
    _made_dirs: list[Path] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        self.quicklook = None if self.quicklook is None else Path(self.quicklook)
        self.format = output_format(self.path)   # its OutputFormat: files, sinks, finishing
        if self.quicklook is not None and self.quicklook.suffix.lower() != ".png":
            raise InputError(self.quicklook, "the quicklook must be a .png file", "name it <something>.png")
        self._sink = self._meta = None
        self._layers = self._layers_spec = None
        self._publishing: FileLock | None = None

    @property
    def provenance_path(self) -> Path | None:
        """The provenance sibling (COG: ``<stem>_provenance.tif``; ENVI: its header), None for Zarr
        (the layers are variables of the store) or without ``provenance``."""
        return self.format.sibling(self.path) if self.provenance else None

    def _temp(self, final: Path, tag: str = "") -> Path:
        tmp = final.with_name(f".{final.name}.partial-{os.getpid()}@{host_name()}{tag}")
        self._temps.append(tmp)
        return tmp

    @property
    def finals(self) -> list[Path]:
        """Every path this output will occupy (ENVI: data and header; plus the quicklook)."""
        paths = self.format.files(self.path)
        sibling = self.provenance_path
        if sibling is not None:
            paths += self.format.files(sibling)
        return paths + [self.item_path] + ([self.quicklook] if self.quicklook is not None else [])

    @property
    def _lock_path(self) -> Path:
        return self.path.with_name(f".{self.path.name}.publish.lock")

    @property
    def item_path(self) -> Path:
        """The output's STAC Item, ``<out>.json`` (:mod:`archive.catalog.product`)."""
        return self.path.with_name(self.path.name + ".json")

    def check(self) -> None:
        """OutputExistsError if a final path exists and overwrite is off; InputError for a parent
        that is not a directory or not writable.

        Also removes the temporaries a killed earlier run left beside a final path (their process,
        named in the temporary's name, no longer runs on this machine).
        """
        stale = FileLock(self._lock_path, "checking")
        if path_exists(stale.path) and stale.try_acquire() is None:   # a killed publisher's (see FileLock)
            stale.release()
        for final in self.finals:
            _remove_stale_temps(final)
            if final.parent.exists() and not final.parent.is_dir():
                raise InputError(final.parent, "is not a directory", "choose another output path")
            if path_exists(final) and not self.overwrite:
                raise OutputExistsError(final)
            if path_exists(final) and final.is_dir() != (final.suffix.lower() == ".zarr"):
                raise InputError(final, "exists and is of another kind (file vs directory)",
                                 "remove it or choose another output path")
            _check_writable(final.parent)

    def _make_dirs(self) -> None:
        for final in self.finals:
            missing = [d for d in (final.parent, *final.parent.parents) if not d.exists()]
            try:
                final.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise unwritable_output(final.parent, exc) from None
            self._made_dirs.extend(missing)  # deepest first: removed again if left empty

    def sink(self, meta: OutputMeta):
        """Create the temporary output of ``meta`` (metadata only, no pixels) and return its sink."""
        if self._sink is not None:
            raise RuntimeError(f"{self.path}: sink created twice")
        self.check()
        self._make_dirs()
        grid = meta.grid
        if self.remote is not None:   # the bucket's old output goes now: its Item first, then its objects
            storage.delete(self.remote + ".json")
            remove_path(self.remote)
        try:
            sink = self.format.create(self._temp, self.path, meta)
            if self.remote is not None:
                import dataclasses

                sink = dataclasses.replace(sink, remote=self.remote)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                size = meta.nbands * grid.height * grid.width * 4
                raise InputError(self.path.parent, f"not enough free space for a {size / 1e9:.1f} GB output",
                                 "free some space or choose another folder") from None
            raise unwritable_output(self.path.parent, exc) from None
        self._sink, self._meta = sink, meta
        return sink

    def layers_sink(self, spec):
        """Create the temporary provenance output of the layers ``spec`` (an
        :class:`~archive.geometry.provenance.ProvenanceSpec`; after :meth:`sink`) and return its sink: layer
        variables of a Zarr store, or an ENVI / COG sink of one band per layer for the sibling file."""
        if self._sink is None or not self.provenance:
            raise RuntimeError(f"{self.path}: layers_sink needs provenance=True and the values sink first")
        try:
            layers = self.format.create_layers(self._temp, self.path, self._sink, self._meta, spec)
        except OSError as exc:
            raise unwritable_output(self.path.parent, exc) from None
        self._layers, self._layers_spec = layers, spec
        return layers

    def finalize(self, sink=None) -> None:
        """Finish the output (its format's: ENVI header, COG layout; the quicklook) and rename
        everything into place; an existing Item (of the output being replaced) is removed first, so
        that no reader takes the new data for the output the old Item describes (the caller writes
        the new Item last)."""
        sink = self._sink if sink is None else sink
        meta = self._meta
        moves: list[tuple[Path, Path]] = []
        if self._layers is not None:
            moves += self.format.finish_layers(self._temp, self.path, self._layers, meta, self._layers_spec)
        done, read_band = self.format.finish(self._temp, self.path, sink, meta)
        moves += done
        if self.quicklook is not None:
            tmp = self._temp(self.quicklook)
            quicklook_png(read_band, meta.grid, meta.wavelengths, meta.nbands, tmp)
            moves.append((tmp, self.quicklook))
        self._publishing = FileLock(self._lock_path, f"publishing {self.path}", what=f"output {self.path}")
        self._publishing.acquire(wait=float("inf"))   # released by cleanup(), after the Item
        self.check()  # something may have appeared meanwhile
        remove_path(self.item_path)   # the old output is no longer complete from here on
        for tmp, final in moves:
            replace_path(tmp, final)
        test_kill("after-data")   # (tests: killed after the data is in place, before its Item)

    def cleanup(self) -> None:
        """Remove every temporary this output created (never the final paths); end its turn to publish."""
        if self._publishing is not None:
            self._publishing.release()
            self._publishing = None
        for tmp in self._temps:
            remove_path(tmp)
        self._temps.clear()
        for d in self._made_dirs:
            try:
                d.rmdir()  # only when empty: after a failure, leave no trace at all
            except OSError:
                pass
        self._made_dirs.clear()


def unwritable_output(where: Path, exc: OSError) -> InputError:
    """The one-line error for an output folder that cannot be written (``exc``: why)."""
    why = storage.reason(exc) or exc.strerror or " ".join(str(exc).split())[:200]   # a server's answer: one line
    return InputError(where, f"cannot write there ({why})", "choose an output folder you can write to")


def _check_writable(folder: Path) -> None:
    """InputError unless ``folder`` (or, when it does not exist yet, its nearest existing parent)
    lets this process create files."""
    existing = next((d for d in (folder, *folder.parents) if d.exists()), None)
    if existing is not None and existing.is_dir() and not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(existing, "is not writable", "choose an output folder you can write to")


#: Zarr metadata file names: uploaded after the data files of a store.
_ZARR_METADATA = {"zarr.json", ".zgroup", ".zattrs", ".zarray", ".zmetadata"}


class RemoteOutput:
    """An output at an ``s3://`` URL: ``local`` (an :class:`Output` in a staging folder of this
    machine, ``$TMPDIR``) is rendered and published there as usual, then :meth:`upload` puts it in
    the bucket, its Item last. Local disk needed: one copy of the output (the staging copy is
    removed by :meth:`cleanup`).

    Use: ``remote = RemoteOutput(url, overwrite, ...)``; ``remote.check()``; render into
    ``remote.local`` (an :class:`Output`); publish it; ``remote.upload()``; always ``remote.cleanup()``.
    """

    def __init__(self, url: str, overwrite: bool = False, quicklook: str | None = None, **output_options):
        import tempfile

        self.url = storage.location(url)
        self.overwrite = bool(overwrite)
        if quicklook is not None and storage.is_url(quicklook):
            raise InputError(quicklook, "a quicklook cannot be written to object storage",
                             "give a local --quicklook path, or none")
        #: a Zarr output's chunks are written by the tile tasks straight into the bucket (no local copy)
        self.direct = self.url.name.lower().endswith(".zarr")
        if self.direct and quicklook is not None:
            raise InputError("--quicklook", "a Zarr output in object storage has no quicklook (its values are only "
                             "in the bucket)", "leave --quicklook out, or render to a local file")
        self.staging = Path(tempfile.mkdtemp(prefix="archive-staging-"))
        self.local = Output(self.staging / self.url.name, overwrite=True, quicklook=quicklook,
                            remote=str(self.url) if self.direct else None, **output_options)
        self._publishing: FileLock | None = None

    def _remote(self, local: Path):
        """The URL of a local final path of :attr:`local` (same name beside :attr:`url`)."""
        return self.url.with_name(local.name)

    def data_urls(self) -> list:
        """The URLs of the output's data (ENVI: data and header; a provenance sibling too)."""
        files = list(self.local.format.files(self.local.path))
        sibling = self.local.provenance_path
        if sibling is not None:
            files += self.local.format.files(sibling)
        return [self._remote(p) for p in files]

    @property
    def item_url(self):
        """The output's STAC Item in the bucket, ``<out>.json``."""
        return self._remote(self.local.item_path)

    def check(self) -> None:
        """OutputExistsError if the output (an object or a prefix) or its Item is in the bucket and
        overwrite is off."""
        if self.overwrite:
            return
        for url in [*self.data_urls(), self.item_url]:
            if path_exists(url):
                raise OutputExistsError(url)

    def upload(self) -> None:
        """Put the published staging output in the bucket: old Item deleted, old objects deleted,
        new files uploaded (metadata of a Zarr store last), Item last. Holds the output's publish
        lock object (``.<name>.publish.lock``) meanwhile: two publishers of one URL take turns."""
        from concurrent.futures import ThreadPoolExecutor

        self._publishing = FileLock(self.url.with_name(f".{self.url.name}.publish.lock"), f"publishing {self.url}",
                                    what=f"output {self.url}")
        self._publishing.acquire(wait=float("inf"))
        try:
            files = [f for f in self.local.format.files(self.local.path)]
            sibling = self.local.provenance_path
            if sibling is not None:
                files += self.local.format.files(sibling)
            if not self.direct:   # (a direct Zarr output's old objects went before its chunks were written)
                self.check()   # something may have appeared meanwhile
                storage.delete(self.item_url)   # the old output is no longer complete from here on
                for local in files:
                    remove_path(self._remote(local))
            puts: list[tuple[Path, object]] = []
            for local in files:
                if local.is_dir():
                    for p in sorted(q for q in local.rglob("*") if q.is_file()):
                        puts.append((p, self._remote(local) / p.relative_to(local).as_posix()))
                elif local.is_file():
                    puts.append((local, self._remote(local)))
            data = [(p, u) for p, u in puts if p.name not in _ZARR_METADATA]
            meta = [(p, u) for p, u in puts if p.name in _ZARR_METADATA]

            def put(pair) -> None:
                storage.write_bytes(pair[1], pair[0].read_bytes())

            with ThreadPoolExecutor(8) as pool:
                list(pool.map(put, data))
                list(pool.map(put, meta))
            text = self.local.item_path.read_text()
            text = text.replace(str(self.local.path), str(self.url))   # the recipe's --out names the URL
            storage.write_bytes(self.item_url, text.encode())   # last: the output is complete from here on
        finally:
            self._publishing.release()
            self._publishing = None

    def cleanup(self) -> None:
        """Remove the staging folder (and the local output's temporaries)."""
        import shutil

        self.local.cleanup()
        if self._publishing is not None:
            self._publishing.release()
            self._publishing = None
        shutil.rmtree(self.staging, ignore_errors=True)
