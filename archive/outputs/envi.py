"""The ENVI output: a BSQ data file written by positioned writes, and its header, built once.

:class:`EnviSink` writes float32 little-endian (band, y, x) into a data file preallocated at its
final size (no memory map); :func:`envi_header` is the one header builder (values and provenance
layers); :data:`FORMAT` (:class:`EnviFormat`) is the format's entry of the registry (:mod:`archive.outputs.registry`):
the data file and then the header (what readers open) are renamed into place, header last.

The writes go through one thread per process (:data:`WRITER`): a file's buffered writes hold its
inode's lock while they copy into the page cache, so two task threads writing one file took turns,
the waiting one spinning on the lock, then asleep (the held-out flight: a task thread asleep on that
lock in 4.0 of the task stream's 5.3 idle core-seconds, and the spinning 3 % of the machine's CPU
samples; bench/RESULTS.md, issue 37). A task thread fills one of its :data:`WRITE_BUFFERS` strip
buffers while earlier ones are being written, and waits only when all are; a tile's writer returns
once its writes are in the file (or raises their error).
"""

from __future__ import annotations

import errno
import os
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.catalog.product import ENVI_MEDIA_TYPE, TEXT_MEDIA_TYPE
from archive.errors import InputError
from archive.formats.envi import header_text
from archive.grid import Grid
from archive.outputs.base import CHUNK, OutputFormat, OutputMeta, Sink, TileWriter, check_bands, check_tile
from archive.outputs.layers import sibling_path

__all__ = ["ENVI_STRIP_MAX", "FORMAT", "WRITER", "WRITE_BUFFERS", "EnviFormat", "EnviSink", "envi_data_path",
           "envi_header", "map_info"]


#: Widest ENVI tile (px): tiles are CHUNK rows x up to this many columns. Mosaics up to this wide are
#: written in whole-width row strips; wider ones in strips of this width, so that the renders a tile
#: waits for stay those near it (a whole-width strip of a wide flight would touch every pass).
ENVI_STRIP_MAX = 4 * CHUNK
#: Strip buffers per task thread: one being filled while the others are written (each CHUNK rows x
#: the strip's width x 4 B: 12 MB for the held-out flight's 2897 px).
WRITE_BUFFERS = 3


class _Writer:
    """The process's one ENVI writing thread (started on first use, again in a forked child)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self._pid = 0
        self._local = threading.local()

    def submit(self, fn, *args) -> Future:
        """Run ``fn(*args)`` on the writing thread, after the writes submitted before."""
        with self._lock:
            if self._pool is None or self._pid != os.getpid():
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="archive-envi-write")
                self._pid = os.getpid()
            return self._pool.submit(fn, *args)

    def buffer(self, width: int) -> tuple[int, np.ndarray, Future | None]:
        """(slot, buffer, write): the calling thread's next (CHUNK, width) float32 strip buffer and
        the write that last read it (None, or a Future the caller waits for before filling it; its
        error, if any, is the tile's that submitted it, which waits for its own writes before it
        ends: see :meth:`_EnviTileWriter.close`)."""
        rings = getattr(self._local, "rings", None)
        if rings is None:
            rings = self._local.rings = {}
        ring = rings.get(width)
        if ring is None:
            if len(rings) > 1:   # strips of several outputs' widths: two kept at most (a write
                rings.clear()    # still running holds its buffer: it ends before its tile does)
            ring = rings[width] = {"next": 0, "buffers": [], "pending": [None] * WRITE_BUFFERS}
        slot = ring["next"]
        ring["next"] = (slot + 1) % WRITE_BUFFERS
        if slot == len(ring["buffers"]):
            ring["buffers"].append(np.empty((CHUNK, width), np.float32))
        return slot, ring["buffers"][slot], ring["pending"][slot]

    def hold(self, width: int, slot: int, future: Future) -> None:
        """Note that the write ``future`` reads buffer ``slot`` of the calling thread's ring."""
        self._local.rings[width]["pending"][slot] = future


#: The process's ENVI writing thread and its per-thread strip buffers.
WRITER = _Writer()


def _pwrite_all(fd: int, data, offset: int) -> None:
    """``os.pwrite`` all of ``data`` (a buffer) at byte ``offset`` (a short write continues)."""
    view = memoryview(data).cast("B")
    while len(view):
        done = os.pwrite(fd, view, offset)
        view, offset = view[done:], offset + done


def _pwrite_rows(fd: int, rows: np.ndarray, offset: int, stride: int) -> None:
    """Write each row of ``rows`` (h, w) at ``offset + r * stride`` bytes."""
    for r in range(rows.shape[0]):
        _pwrite_all(fd, rows[r], offset + r * stride)


@dataclass(frozen=True)
class EnviSink(Sink):
    """ENVI BSQ data file being written: float32 little-endian (band, y, x), preallocated.

    Its tiles are CHUNK rows x up to ENVI_STRIP_MAX columns (:attr:`tile_size`): a mosaic at most
    that wide is written in whole-width row strips, each band of a strip with ONE ``os.pwrite`` (a
    band's rows are contiguous in BSQ; a 1024-px tile took one call per row, ~5 us each: seconds of
    CPU for a 300-band mosaic); wider mosaics one call per row of 4 x 1024 px. Nothing is
    memory-mapped: the written pages are the page cache's, not the process's.
    """

    data: str
    nbands: int
    height: int
    width: int

    @property
    def tile_size(self) -> tuple[int, int]:
        """(height, width) of the graph's output tiles for this sink, pixels."""
        return (CHUNK, min(self.width, ENVI_STRIP_MAX))

    @classmethod
    def create(cls, data: str | os.PathLike, nbands: int, height: int, width: int) -> EnviSink:
        """Create the data file at its full size (space reserved when the file system can:
        a full disk fails here, before any rendering)."""
        size = nbands * height * width * 4
        fd = os.open(data, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            try:
                os.posix_fallocate(fd, 0, size)
            except OSError as exc:
                if exc.errno == errno.ENOSPC:
                    raise
                os.ftruncate(fd, size)  # no fallocate here (EOPNOTSUPP, EINVAL): a sparse file
        finally:
            os.close(fd)
        return cls(os.fspath(data), nbands, height, width)

    def open_tile(self, band0: int, tile, nbands: int) -> _EnviTileWriter:
        check_tile(tile, self.height, self.width, self.tile_size)
        check_bands(band0, nbands, self.nbands, f"of a {self.nbands}-band ENVI file")
        return _EnviTileWriter(self, band0, tile)


class _EnviTileWriter(TileWriter):
    """A tile's writer: ``buffer()`` hands out the thread's strip buffers in turn; ``write`` queues
    the band's write on :data:`WRITER` (a buffer not handed out by ``buffer()`` is written at once);
    ``close`` waits for the tile's writes and raises the first error."""

    def __init__(self, sink: EnviSink, band0: int, tile):
        super().__init__(band0, tile)
        self.sink = sink
        self.fd = os.open(sink.data, os.O_WRONLY)
        self.width = sink.tile_size[1]
        self.writes: list[Future] = []
        self.lent: tuple[int, np.ndarray] | None = None

    def buffer(self) -> np.ndarray:
        slot, buffer, pending = WRITER.buffer(self.width)
        if pending is not None:
            pending.exception()   # waits; a failed write is its own tile's error (raised by its close)
        self.lent = (slot, buffer)
        return buffer

    def write(self, b: int, chunk: np.ndarray) -> None:
        row0, col0, h, w = self.tile
        s = self.sink
        lent, self.lent = self.lent, None
        if sys.byteorder != "little":
            chunk, lent = chunk.astype("<f4"), None
        base = (((self.band0 + b) * s.height + row0) * s.width + col0) * 4
        if w == s.width:  # whole rows: one contiguous range
            if w != chunk.shape[1]:
                chunk, lent = np.ascontiguousarray(chunk[:h, :w]), None
            args = (_pwrite_all, self.fd, chunk[:h], base)
        else:
            args = (_pwrite_rows, self.fd, chunk[:h, :w], base, s.width * 4)
        if lent is None or lent[1] is not chunk:   # not the thread's strip buffer: written now
            args[0](*args[1:])
            return
        future = WRITER.submit(*args)
        WRITER.hold(self.width, lent[0], future)
        self.writes.append(future)

    def _finish(self) -> BaseException | None:
        """Wait for the tile's writes and close the file; the first write's error, or None."""
        try:
            errors = [f.exception() for f in self.writes]
        finally:
            self.writes = []
            os.close(self.fd)
        return next((e for e in errors if e is not None), None)

    def close(self):
        error = self._finish()
        if error is not None:
            raise error

    def abort(self) -> None:
        self._finish()


def map_info(grid: Grid) -> str:
    """ENVI ``map info`` of ``grid``: UTM zone and hemisphere for a WGS 84 / UTM EPSG, else Arbitrary."""
    zone, north = None, True
    if 32601 <= grid.epsg <= 32660:
        zone = grid.epsg - 32600
    elif 32701 <= grid.epsg <= 32760:
        zone, north = grid.epsg - 32700, False
    if zone is None:
        return f"{{Arbitrary, 1, 1, {grid.x0!r}, {grid.y0!r}, {grid.gsd!r}, {grid.gsd!r}, units=Meters}}"
    hemisphere = "North" if north else "South"
    return (f"{{UTM, 1, 1, {grid.x0!r}, {grid.y0!r}, {grid.gsd!r}, {grid.gsd!r}, {zone}, {hemisphere}, "
            f"WGS-84, units=Meters}}")


def envi_data_path(header: str | os.PathLike) -> Path:
    """The BSQ data file of an ENVI output ``<name>.hdr``: ``<name>`` (the header path minus .hdr)."""
    header = Path(header)
    return header.with_name(header.name[: -len(".hdr")]) if header.name.lower().endswith(".hdr") else header


def envi_header(grid: Grid, nbands: int, description: str, band_names, extra: dict | None = None) -> str:
    """The ENVI header text of a float32 little-endian BSQ file on ``grid``: ``nbands`` bands named
    ``band_names`` (commas replaced), its ``map info`` and WKT, NaN as the ignore value, then the
    ``extra`` keys in their order; written by the package's one ENVI header writer,
    :func:`archive.formats.envi.header_text`."""
    return header_text({
        "description": description,
        "samples": grid.width,
        "lines": grid.height,
        "bands": nbands,
        "header offset": 0,
        "file type": "ENVI Standard",
        "data type": 4,
        "interleave": "bsq",
        "byte order": 0,
        "map info": map_info(grid),
        "coordinate system string": grid.crs.to_wkt(version="WKT1_ESRI"),
        "data ignore value": "NaN",
        "band names": [name.replace(",", ";") for name in band_names],
        **(extra or {}),
    })


def values_header(meta: OutputMeta) -> str:
    """The header of a rendered mosaic (``wavelength`` and ``fwhm`` in nm when known)."""
    extra: dict[str, object] = {}
    if meta.wavelengths is not None:
        extra["wavelength units"] = "Nanometers"
        extra["wavelength"] = [f"{w:.4f}" for w in meta.wavelengths]
    if meta.fwhm is not None:  # in 'wavelength units' (nm), which ENVI applies to fwhm too
        extra["wavelength units"] = "Nanometers"
        extra["fwhm"] = [f"{w:.4f}" for w in meta.fwhm]
    return envi_header(meta.grid, meta.nbands, f"archive render mosaic: {meta.variable}, NaN where not covered",
                       meta.labels, extra)


def layers_header(grid: Grid, spec) -> str:
    """The header of the provenance layers' BSQ (float32 little-endian, NaN = no source)."""
    return envi_header(grid, len(spec.names), f"archive render provenance layers; NaN where not covered; time: "
                       f"{spec.time_units}", spec.names, {
                           "time reference": spec.reference_utc,
                           # cube index i of the 'cube' layer = the i-th entry: <source id>/<cube file base name>
                           "provenance cubes": [f"{c['source']}/{c['cube']}" for c in spec.cubes]})


def read_band(data: str | os.PathLike, grid: Grid, b: int, step: int) -> np.ndarray:
    """Every step-th pixel of band b of a BSQ float32 file, read row by row (pread)."""
    rows = range(0, grid.height, step)
    out = np.empty((len(rows), -(-grid.width // step)), np.float32)
    fd = os.open(data, os.O_RDONLY)
    try:
        for k, r in enumerate(rows):
            raw = os.pread(fd, grid.width * 4, ((b * grid.height + r) * grid.width) * 4)
            out[k] = np.frombuffer(raw, "<f4")[::step]
    finally:
        os.close(fd)
    return out


class EnviFormat(OutputFormat):
    """The ENVI format (:class:`~archive.outputs.base.OutputFormat`): ``<name>`` (data) +
    ``<name>.hdr``; provenance layers in a sibling ``<stem>_provenance`` + ``.hdr``."""

    name = "envi"
    suffixes = (".hdr",)
    label = "ENVI BSQ"
    media_type = ENVI_MEDIA_TYPE
    sink = EnviSink

    def files(self, path: Path) -> list[Path]:
        return [*self.sidecars(path), path]   # the data file first: it is renamed into place first

    def sidecars(self, path: Path) -> list[Path]:
        return [envi_data_path(path)]

    def sibling(self, path: Path) -> Path | None:
        return sibling_path(path)

    @staticmethod
    def create(temp, path: Path, meta: OutputMeta) -> EnviSink:
        return EnviSink.create(temp(envi_data_path(path)), meta.nbands, meta.grid.height, meta.grid.width)

    def create_layers(self, temp, path: Path, sink, meta: OutputMeta, spec) -> EnviSink:
        data = temp(envi_data_path(self.sibling(path)))
        return EnviSink.create(data, len(spec.names), meta.grid.height, meta.grid.width)

    @staticmethod
    def finish(temp, path: Path, sink: EnviSink, meta: OutputMeta):
        header = temp(path)
        header.write_text(values_header(meta), encoding="ascii")
        moves = [(Path(sink.data), envi_data_path(path)), (header, path)]   # header last
        return moves, lambda b, step: read_band(sink.data, meta.grid, b, step)

    def finish_layers(self, temp, path: Path, layers: EnviSink, meta: OutputMeta, spec) -> list:
        sibling = self.sibling(path)
        header = temp(sibling)
        header.write_text(layers_header(meta.grid, spec), encoding="ascii")
        return [(Path(layers.data), envi_data_path(sibling)), (header, sibling)]

    def stac_assets(self, out: Path, href, variable: str, data: dict) -> dict[str, dict]:
        if out.suffix != ".hdr":
            raise InputError(out, "an ENVI output is named by its header, PATH.hdr")
        return {"data": {"href": href(envi_data_path(out)), "type": self.media_type,
                         "title": f"{variable} ({self.label}, float32 little-endian, NaN where not covered)", **data},
                "header": {"href": href(out), "type": TEXT_MEDIA_TYPE, "title": "ENVI header",
                           "roles": ["metadata"]}}

    def provenance_assets(self, provenance: Path, href, fields: dict, describe) -> dict[str, dict]:
        data = envi_data_path(provenance)
        bands, names = describe(data)
        return {"provenance": {"href": href(data), "type": self.media_type,
                               "title": f"Provenance layers ({self.label} data)", "roles": ["metadata"], **fields,
                               "raster:bands": bands, "archive:layers": names},
                "provenance_header": {"href": href(provenance), "type": TEXT_MEDIA_TYPE,
                                      "title": "ENVI header of the provenance layers", "roles": ["metadata"]}}


#: The ENVI format's entry of :mod:`archive.outputs.registry`.
FORMAT = EnviFormat()
