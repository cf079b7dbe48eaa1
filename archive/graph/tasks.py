"""Task bodies of the render graph: plain module-level functions of explicit inputs.

They run on Dask workers but can be called directly (tests, debugging). Boxes are
``(row0, col0, height, width)`` in pixels of the output grid; rasters are ``(band, y, x)``.

GL work (the lookup pass and the band passes) runs on the process's one GL thread
(:func:`gl_call`), whichever worker thread runs the task: the OpenGL context lives there, made once,
and the worker's other threads mosaic, encode and write meanwhile. A render task reads its bands
and radiometry in its own thread first, so a second render task admitted by the worker's ``GPU``
resource reads while the first one draws.

Writer tasks write through a *sink* (:mod:`archive.outputs`: Zarr store, ENVI file or COG spool),
one output tile of one band group each.
"""

from __future__ import annotations

import math
import sys
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from archive.errors import InputError, RenderError
from archive.files import test_hold_calls
from archive.grid import Grid
from archive.overlap import OverlapRule

Box = tuple[int, int, int, int]

__all__ = ["Box", "assemble_layers", "assemble_task", "assemble_write_task", "blank_write_task", "band_pass", "band_pass_choice",
           "cpu_band_pass", "decided_band_pass", "gate_task", "gl_call", "layout_task",
           "layers_task", "lookup_task", "PackedLookup", "ValuesPool", "VALUES_POOL", "unpacked", "overview_task", "pick_task", "render_task", "write_layers_task",
           "write_saturated_task", "write_values_task"]

_GL_LOCK = threading.Lock()
_GL_EXECUTOR: list[ThreadPoolExecutor] = []


def gl_call(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` run on this process's GL thread (one per process, made on first use,
    named 'archive-gl'), the calling thread waiting for it: every GL call of the process goes through
    one thread, so one context serves them all (a context belongs to the thread that made it)."""
    with _GL_LOCK:
        if not _GL_EXECUTOR:
            _GL_EXECUTOR.append(ThreadPoolExecutor(1, thread_name_prefix="archive-gl"))
        executor = _GL_EXECUTOR[0]
    return executor.submit(fn, *args, **kwargs).result()


_BAND_PASS: dict[str, object] = {}


def _band_pass_facts() -> tuple[str, str | None]:
    """(GL renderer string, why compute shaders cannot run or None): on the GL thread."""
    from archive.render.compute import compute_unsupported
    from archive.render.context import gl_info

    return str(gl_info().get("renderer")), compute_unsupported()


def band_pass_choice():
    """How this process's render tasks compute the per-band gather: an
    :class:`archive.render.gather.BandPass` (method 'cpu', 'gl' or 'compute', and the reason), from
    :func:`archive.render.gather.band_pass_choice` on its GL thread's renderer and the setting
    ``ARCHIVE_BAND_PASS``; decided once per process and setting. Its ``method`` is what a render's
    metadata records (:func:`band_pass`)."""
    import os

    from archive.render.gather import band_pass_choice as choose

    setting = os.environ.get("ARCHIVE_BAND_PASS") or "auto"
    with _GL_LOCK:
        known = _BAND_PASS.get(setting)
    if known is None:
        if setting.strip().lower() in ("cpu", "gl"):   # no GL context needed to know it
            known = choose(None, setting)
        else:
            renderer, unsupported = gl_call(_band_pass_facts)
            known = choose(renderer, setting, compute_unsupported=unsupported)
        with _GL_LOCK:
            _BAND_PASS[setting] = known
    return known


def decided_band_pass() -> dict | None:
    """The band pass this process's render tasks took, as decided so far: {'method': 'cpu' | 'gl' |
    'compute', 'reason': ...} for the current ``ARCHIVE_BAND_PASS``, or None when no render task
    (nor :func:`band_pass`) has decided it here. Makes no GL context and decides nothing: for
    ``client.run(decided_band_pass)`` after a render, to record in the output's metadata."""
    import os

    with _GL_LOCK:
        known = _BAND_PASS.get(os.environ.get("ARCHIVE_BAND_PASS") or "auto")
    return None if known is None else {"method": known.method, "reason": known.reason}


def band_pass() -> str:
    """The band-pass method of this process's render tasks: 'cpu', 'gl' or 'compute' (:func:`band_pass_choice`)."""
    return band_pass_choice().method


def cpu_band_pass() -> bool:
    """Whether this process's render tasks gather their bands on the CPU (:func:`band_pass` is 'cpu':
    on a software GL renderer such as llvmpipe) rather than in GL (fragment passes or compute)."""
    return band_pass() == "cpu"


class ValuesPool:
    """Float32 buffers for render tasks' values, reused once the graph has released them.

    A render's values (bands x window px x 4 B: ~50 MB for 8 bands of a paper cube) live until the
    writers of every tile they touch have run; a fresh array of that size is fresh pages (memory
    mapped on its own, :func:`_new_buffer`) that the kernel zeroes and faults in, which cost the CPU
    gather ~40 % more on the paper flight. :meth:`take` gives an array backed by a free buffer of
    about the right size (at most ``slack`` times larger) or a new one; when every array (and view)
    of it is gone (the graph released the render), its buffer comes back here. At most ``keep``
    buffers wait free (a bounded addition to the renders held), and in a Dask worker with a memory
    limit at most ``share`` of that limit: a small worker keeps none (free buffers are memory the
    worker cannot give back; a 500 MB worker paused above its 80 % and, with nothing left to run
    that would release memory, never resumed)."""

    def __init__(self, keep: int = 2, slack: float = 1.5, share: float = 0.05):
        self.keep, self.slack, self.share = keep, slack, share
        self.free: list[np.ndarray] = []
        self.cap = math.inf   # bytes the free buffers may take (set from the worker's memory limit)
        self.lock = threading.Lock()

    def _worker_cap(self) -> float:
        """``share`` of the memory limit of the Dask worker running this task, inf outside one or
        without a limit (distributed is not imported here: only looked up if loaded)."""
        distributed = sys.modules.get("distributed")
        if distributed is None:
            return math.inf
        try:
            limit = distributed.get_worker().memory_manager.memory_limit
        except (ValueError, AttributeError):   # not in a worker's task
            return math.inf
        return self.share * limit if limit else math.inf

    def take(self, shape: tuple[int, ...]) -> np.ndarray:
        """An uninitialised C-contiguous float32 array of ``shape`` (values of one render)."""
        import weakref

        n = int(np.prod(shape))
        self.cap = self._worker_cap()
        with self.lock:
            fits = [k for k, raw in enumerate(self.free) if n <= raw.size <= self.slack * n]
            raw = self.free.pop(min(fits, key=lambda k: self.free[k].size)) if fits else None
        if raw is None:
            raw = _new_buffer(n)
        # ``flat`` does not own its memory and its base is no array, so every view of it (the
        # reshaped values, the slices writers take) has ``flat`` as its base: it dies with the last
        # of them, and only then is the buffer free again
        flat = np.frombuffer(memoryview(raw), np.float32, count=n)
        weakref.finalize(flat, self._give_back, raw)
        return flat.reshape(shape)

    def _give_back(self, raw: np.ndarray) -> None:
        with self.lock:
            self.free.append(raw)
            while self.free and (len(self.free) > self.keep or sum(r.nbytes for r in self.free) > self.cap):
                self.free.pop(0)


#: Buffers of at least this many bytes are anonymous memory maps of their own (:func:`_new_buffer`).
OWN_MAPPING_BYTES = 1024**2


def _new_buffer(n: int) -> np.ndarray:
    """A new (n,) float32 buffer: from numpy (glibc) when small, else an anonymous memory map of
    its own, unmapped (returned to the system) as soon as the pool drops it. glibc serves
    allocations under its mmap threshold (32 MiB in our workers, :data:`archive.run.cluster.MALLOC_MMAP_THRESHOLD`)
    from its heaps, which keep the memory once freed: render values of 5 bands of a paper cube
    (32.2 MB) held the worker 0.1 GB higher than 6-band ones (38.6 MB, mapped) on the 40-cube flight."""
    if n * 4 < OWN_MAPPING_BYTES:
        return np.empty(n, np.float32)
    import mmap

    mapping = mmap.mmap(-1, n * 4, flags=mmap.MAP_PRIVATE)
    # as numpy does for its large arrays: first touch of a 62 MB buffer 28 -> 6 ms (transparent huge
    # pages 'madvise'); a kernel without them refuses the advice, and the buffer is used as it is
    try:
        mapping.madvise(mmap.MADV_HUGEPAGE)
    except (AttributeError, OSError):
        pass
    return np.frombuffer(mapping, np.float32, count=n)


#: The process's pool of render values (worker processes: one per process, shared by its threads).
VALUES_POOL = ValuesPool()


class PackedLookup:
    """A :class:`archive.render.renderer.Lookup` as the graph holds it between its lookup task and
    the render tasks of every band group: its flat gather index
    (:class:`archive.render.gather.GatherIndex`, ``line * samples + sample`` over the covered rows)
    and its count compressed (Blosc LZ4 with byte shuffle), so that the lookups held for a whole
    flight stay small (8 B per window pixel unpacked: 480 MB for the paper's 40 cubes) and a render
    decodes the index it gathers through in one step (:meth:`gather_index`) instead of unpacking
    line and sample and rebuilding it. Picklable; :meth:`unpack` gives the Lookup back, equal array
    for array (a lookup whose line and sample are not both -1 at the same pixels, or out of the
    cube, which pass 1 never makes, also keeps them as they are)."""

    def __init__(self, lookup):
        import numcodecs

        from archive.render.gather import gather_index

        codec = numcodecs.Blosc("lz4", 5, numcodecs.Blosc.SHUFFLE)
        self.grid, self.lines, self.samples = lookup.grid, lookup.lines, lookup.samples
        gather = gather_index(lookup)
        self.row0, self.height, self.dtype = gather.row0, gather.height, gather.index.dtype
        self.index = codec.encode(gather.index)
        self.count = None if lookup.count is None else codec.encode(lookup.count)
        line, sample = lookup.line, lookup.sample
        regular = (np.array_equal(line < 0, sample < 0) and np.min(line, initial=0) >= -1
                   and np.min(sample, initial=0) >= -1 and np.max(line, initial=-1) < lookup.lines
                   and np.max(sample, initial=-1) < lookup.samples)
        self.pairs = None if regular else codec.encode(np.stack([line, sample]))

    @property
    def nbytes(self) -> int:
        return len(self.index) + sum(0 if b is None else len(b) for b in (self.count, self.pairs))

    def gather_index(self):
        """The :class:`archive.render.gather.GatherIndex` of the lookup (one decode)."""
        import numcodecs

        from archive.render.gather import GatherIndex

        index = np.frombuffer(numcodecs.Blosc().decode(self.index), self.dtype)
        return GatherIndex(self.grid, self.lines, self.samples, self.row0, self.height, index)

    def unpack(self):
        """The :class:`archive.render.renderer.Lookup` (line and sample from the flat index)."""
        import numcodecs

        from archive.render.renderer import Lookup

        codec = numcodecs.Blosc()
        shape = self.grid.shape
        count = (None if self.count is None
                 else np.frombuffer(codec.decode(self.count), np.uint16).reshape(shape))
        if self.pairs is not None:
            pairs = np.frombuffer(codec.decode(self.pairs), np.int32).reshape(2, *shape)
            return Lookup(self.grid, pairs[0], pairs[1], self.lines, self.samples, count)
        gather = self.gather_index()
        line = np.full(shape, -1, np.int32)
        sample = np.full(shape, -1, np.int32)
        rows = slice(self.row0, self.row0 + self.height)
        index = gather.index.reshape(self.height, shape[1])
        covered = index != gather.sentinel
        line[rows] = np.where(covered, index // self.samples, -1)
        sample[rows] = np.where(covered, index % self.samples, -1)
        return Lookup(self.grid, line, sample, self.lines, self.samples, count)


def unpacked(lookup):
    """The Lookup of a :class:`PackedLookup` (a Lookup as it is)."""
    return lookup.unpack() if isinstance(lookup, PackedLookup) else lookup


def lookup_task(mesh, window: Grid, samples: int, *after, count: bool = False):
    """Pass 1 of the renderer for one cube: which (line, sample) each pixel centre of ``window`` sees.

    Runs once per cube (GL, on a worker); returns the picklable :class:`archive.render.renderer.Lookup`
    ((height, width) int32 line and sample, -1 where not covered; with ``count`` also how many mesh
    layers cover each pixel) that every band group reuses, packed (:class:`PackedLookup`).
    ``after``: results of tasks it waits for (the graph's backpressure), not used.
    """
    from archive.render.renderer import rasterize_lookup  # GL only on workers

    return PackedLookup(gl_call(rasterize_lookup, mesh, window, samples, count=count))


def layers_task(source, cube: int, job: int, lookup, spec, ground: float | None) -> np.ndarray:
    """The provenance layers ``spec.names`` (:mod:`archive.geometry.provenance`) of one cube on its window,
    (layers, height, width) float32, NaN where not covered: CPU only, from the cube's lookup and
    navigation (no pixel is read). ground: the flat ground height of its mesh, m (None with a DEM)."""
    from archive.geometry.provenance import cube_layers

    return cube_layers(source, cube, job, unpacked(lookup), spec, ground)


def pick_task(layers: np.ndarray, index: int) -> np.ndarray:
    """Layer ``index`` of a :func:`layers_task` result, (height, width) float32 (a copy: the stack
    can be released while this one is still needed)."""
    return np.array(layers[index])


def render_task(source, cube: int, bands: Sequence[int], lookup, mode: str,
                bands_per_pass: int = 8, *after) -> tuple[np.ndarray, np.ndarray]:
    """Render ``bands`` of ``cube`` of ``source`` through the cube's ``lookup`` (from :func:`lookup_task`).

    Reads the bands and radiometry here, in the task's thread, then draws on the process's GL
    thread (:func:`gl_call`) by the method :func:`band_pass` names: 'gl', ``bands_per_pass`` (1..8)
    bands per full-screen pass; 'compute', a compute shader (:func:`archive.render.compute.compute_lookup`);
    'cpu' (software GL such as llvmpipe) gathers the bands through the lookup with numpy in its own
    thread instead (:func:`archive.render.gather.gather_lookup`). All give equal values (tested). ``after``: results
    of tasks the render waits for (the graph's backpressure, :func:`gate_task`), not used.
    Returns values (len(bands), window height, window width) float32 (NaN where not covered) and
    saturated (window height, window width) bool.
    """
    from archive.render.renderer import render_lookup  # GL only on workers

    bands = list(bands)
    try:
        dn = source.read_bands(cube, bands)
        radiometry = source.radiometry(cube, bands, mode)
        method = band_pass()
        if method in ("cpu", "compute"):   # the gather through the flat index (same values, tested)
            gather = lookup.gather_index() if isinstance(lookup, PackedLookup) else lookup
            out = VALUES_POOL.take((len(bands), *gather.grid.shape))
            if method == "cpu":   # software GL: numpy, in this thread
                from archive.render.gather import gather_lookup

                result = gather_lookup(gather, dn, radiometry, out=out)
            else:                 # GPU: a compute shader on the GL thread, read back into ``out``
                from archive.render.compute import compute_lookup

                result = gl_call(compute_lookup, gather, dn, radiometry, out=out)
        else:
            result = gl_call(render_lookup, unpacked(lookup), dn, radiometry,
                             bands_per_pass=min(bands_per_pass, len(bands)))
    except (InputError, RenderError) as exc:  # say which cube: the renderer cannot know
        where = f"{source.label} cube {source.cubes[cube].base}"
        if isinstance(exc, InputError):
            # keep the kind, problem and fix; name the file too when it is more than the source
            named = exc.where if exc.where not in (None, source.label) else None
            raise type(exc)(where if named is None else f"{where} ({named})", exc.problem, exc.fix) from exc
        raise RenderError(f"{where}: {exc}") from exc
    return result.values, result.saturated


def _overlap(tile: Box, box: Box) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
    """Slices (in the tile, in the box's array) of the pixels the two boxes share, or None."""
    r0 = max(tile[0], box[0])
    c0 = max(tile[1], box[1])
    r1 = min(tile[0] + tile[2], box[0] + box[2])
    c1 = min(tile[1] + tile[3], box[1] + box[3])
    if r1 <= r0 or c1 <= c0:
        return None
    in_tile = (slice(r0 - tile[0], r1 - tile[0]), slice(c0 - tile[1], c1 - tile[1]))
    in_box = (slice(r0 - box[0], r1 - box[0]), slice(c0 - box[1], c1 - box[1]))
    return in_tile, in_box


def _tile_parts(tile: Box, boxes: Sequence[Box], renders) -> list:
    """(values, saturated, tile rows, tile cols) of each render's part inside ``tile``, in order."""
    parts = []
    for box, (values, saturated) in zip(boxes, renders):
        shared = _overlap(tile, box)
        if shared is not None:
            (tr, tc), (br, bc) = shared
            parts.append((values[:, br, bc], saturated[br, bc], tr, tc))
    return parts


def _tile_keys(tile: Box, boxes: Sequence[Box], keys: Sequence[np.ndarray] | None) -> list | None:
    """Each render's key (the layer the rule compares, (h, w)) inside ``tile``, in the order of
    :func:`_tile_parts`; None without keys."""
    if keys is None:
        return None
    if len(keys) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes for {len(keys)} keys")
    out = []
    for box, key in zip(boxes, keys):
        shared = _overlap(tile, box)
        if shared is not None:
            out.append(key[shared[1]])
    return out


def assemble_task(rule: OverlapRule, tile: Box, nbands: int, boxes: Sequence[Box],
                  *renders: tuple[np.ndarray, np.ndarray], keys: Sequence[np.ndarray] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Mosaic cube renders onto one output tile with the overlap ``rule`` (:mod:`archive.overlap`).

    boxes[i]: where renders[i] (values (nbands, h, w), saturated (h, w)) lies in the output grid;
    renders in capture order; keys[i]: the layer the rule compares (:attr:`~archive.overlap.OverlapRule.key`,
    (h, w)) of renders[i], for a rule that compares one.
    Returns values (nbands, tile h, tile w) float32, saturated (h, w) bool.
    """
    if len(boxes) != len(renders):
        raise ValueError(f"{len(boxes)} boxes for {len(renders)} renders")
    return rule.assemble(nbands, tile[2], tile[3], _tile_parts(tile, boxes, renders), _tile_keys(tile, boxes, keys))


def assemble_layers(rule: OverlapRule, tile: Box, names: Sequence[str], boxes: Sequence[Box],
                    *layers: np.ndarray) -> np.ndarray:
    """Provenance layers of one output tile, (len(names), h, w) float32: the layers of the capture
    the mosaic ``rule`` (one with a single source) picks at each pixel (so they describe the written
    value), except 'overlap_count', the SUM over every capture covering the pixel (NaN where none does).

    layers[i]: (len(names), h, w) float32 of the cube at boxes[i] (:func:`layers_task`), capture order.
    """
    names = list(names)
    key_at = names.index(rule.key) if rule.key in names else None
    count_at = names.index("overlap_count") if "overlap_count" in names else None
    mosaic = rule.mosaic(len(names), tile[2], tile[3])
    total = np.zeros(tile[2:], np.float32)
    unflagged = np.zeros(tile[2:], bool)
    for box, stack in zip(boxes, layers):
        shared = _overlap(tile, box)
        if shared is None:
            continue
        (tr, tc), (br, bc) = shared
        part = stack[:, br, bc]
        mosaic.feed(part, unflagged[tr, tc], tr, tc, key=None if key_at is None else part[key_at])
        if count_at is not None:
            total[tr, tc] += np.nan_to_num(part[count_at])
    values, _ = mosaic.result()
    if count_at is not None:
        values[count_at] = np.where(total > 0, total, np.nan)
    return values


def write_layers_task(sink, rule: OverlapRule, tile: Box, names: Sequence[str], boxes: Sequence[Box],
                      *layers: np.ndarray):
    """:func:`assemble_layers` for one output tile, written through the provenance ``sink`` (one
    sink band per layer); returns what the sink's tile writer passes on (COG: its overview quarter)."""
    values = assemble_layers(rule, tile, names, boxes, *layers)
    return write_values_task(sink, 0, tile, (values, None))


#: Test-only: ``ARCHIVE_TEST_HOLD_WRITES=N[:PATH]`` makes each worker process's tile writes after its
#: first N wait (:func:`archive.files.test_hold`: until killed, or while the file PATH exists): a test
#: kills a render, or one of its workers, mid-job at a moment it controls, however loaded the machine
#: (never set outside tests).
TEST_HOLD_WRITES = "ARCHIVE_TEST_HOLD_WRITES"


def write_values_task(sink, band0: int, tile: Box, assembled: tuple[np.ndarray, np.ndarray],
                      saturated_before: np.ndarray | None = None):
    """Write an assembled tile's values (nbands, h, w) through ``sink``, band by band.

    Returns what :func:`assemble_write_task` returns.
    """
    values, saturated = assembled
    test_hold_calls(TEST_HOLD_WRITES)
    with sink.open_tile(band0, tile, values.shape[0]) as writer:
        for b in range(values.shape[0]):
            buffer = writer.buffer()
            buffer[:tile[2], :tile[3]] = values[b]
            buffer[tile[2]:] = np.nan  # the grid's outside part (zarr's padding of edge chunks)
            buffer[:tile[2], tile[3]:] = np.nan
            writer.write(b, buffer)
        passed = writer.close()
    return _result(sink, saturated, saturated_before, passed)


def _result(sink, saturated, saturated_before, passed):
    if not sink.saturation:
        return passed
    return saturated if saturated_before is None else saturated | saturated_before


def assemble_write_task(sink, rule: OverlapRule, band0: int, tile: Box, nbands: int,
                        boxes: Sequence[Box], saturated_before: np.ndarray | None,
                        *renders: tuple[np.ndarray, np.ndarray], keys: Sequence[np.ndarray] | None = None):
    """:func:`assemble_task` and :func:`write_values_task` in one: mosaic the renders of one band
    group onto one output tile (one chunk wide) and write it through ``sink``
    (:class:`~archive.outputs.zarr.MosaicStore`, :class:`~archive.outputs.envi.EnviSink` or
    :class:`~archive.outputs.cog.CogSink`), band by band, by the ``rule``'s own chunk writer
    (:meth:`~archive.overlap.OverlapRule.write_bands`: 'last' and 'nadir' write each band straight
    from the renders into this thread's reusable chunk buffer, building no tile).

    Returns, for a sink that records saturation (Zarr), the tile's saturation mask (h, w) bool OR
    ``saturated_before`` (earlier band groups); for the others what the sink's tile writer passes on
    (COG: the tile's quarter of overview level 2, (nbands, ceil(h/4), ceil(w/4)) float32, or None).
    keys: the layer the rule compares (h, w) of each render, for a rule that compares one.
    """
    if len(boxes) != len(renders):
        raise ValueError(f"{len(boxes)} boxes for {len(renders)} renders")
    parts = _tile_parts(tile, boxes, renders)
    parts_keys = _tile_keys(tile, boxes, keys)
    test_hold_calls(TEST_HOLD_WRITES)
    with sink.open_tile(band0, tile, nbands) as writer:
        saturated = rule.write_bands(writer, nbands, tile[2], tile[3], parts, parts_keys, sink.saturation)
        passed = writer.close()
    return _result(sink, saturated, saturated_before, passed)


def gate_task(*done) -> None:
    """A token that the writers ``done`` have run (renders wait on it: memory backpressure)."""
    return None


def blank_write_task(sink, band0: int, tile: Box, nbands: int):
    """Write NaN into every band of a tile no cube touches (formats without a fill value: ENVI, COG);
    returns what the sink's tile writer passes on (None)."""
    test_hold_calls(TEST_HOLD_WRITES)
    with sink.open_tile(band0, tile, nbands) as writer:
        filled: set[int] = set()   # the buffers set NaN (ENVI's come in turn; the others are one)
        for b in range(nbands):
            buffer = writer.buffer()
            if id(buffer) not in filled:
                buffer[...] = np.nan
                filled.add(id(buffer))
            writer.write(b, buffer)
        return writer.close()


def overview_task(sink, level: int, row: int, col: int, band0: int, nbands: int, *children):
    """Tile (row, col) of overview ``level`` >= 2 of a COG, for bands band0..: the quarters its
    children of the level below computed (their NaN-aware 2 x 2 averages, in
    :meth:`~archive.outputs.cog.CogSink.children` order; None: all NaN or absent), compressed into the
    sink's spool. Returns its own quarter of the next level (or None)."""
    return sink.overview(level, row, col, band0, nbands, children)


def layout_task(sink, band0: int, nbands: int, start: int, *written) -> int:
    """Lay out the full resolution of bands band0.. of a COG (its writer tasks, ``written``, all ran)
    from byte ``start`` of its data file on (:meth:`~archive.outputs.cog.CogSink.lay_out`); returns
    where the next band group starts."""
    return sink.lay_out(band0, nbands, start)


def write_saturated_task(store, tile: Box, *masks: np.ndarray) -> int:
    """OR the saturation masks of one tile and write them through ``store`` (a sink that records
    saturation: its ``write_saturated``); returns the saturated pixel count."""
    mask = np.zeros(tile[2:], bool)
    for m in masks:
        mask |= m
    store.write_saturated(tile[0], tile[1], mask)
    return int(mask.sum())
