"""The collection format, owned here alone: one raw flight ingested into a chunked, compressed
Zarr v3 group — attribute names, codecs, completion marker, chunk paths, digests, the local frame
to and from attributes — written (ingest), verified (verify) and read back (the collection source,
the catalog). No other module knows this layout.

Layout of ``<ARCHIVE>/collections/<id>.zarr`` (axis orders in brackets)::

    dn            [band, line, sample]  raw DN, all cubes' lines in capture order, native dtype
                  (uint16 for Resonon), one chunk = one band x CHUNK_LINES lines (see below)
    dn_sha256     [band, chunk, 32]     sha256 of each decoded dn chunk (C order, little endian)
    time          [line]                line exposure start on the .lcf scale, ingest's sync offset (s)
    camera_time   [line]                the raw .bil.times values (camera clock, s)
    cube          [line]                cube index of each line
    position      [line, 3]             camera N, E, D (m) in the collection frame (ingest's navigation_params)
    attitude      [line, 4]             camera -> NED quaternion (x, y, z, w) (ingest's navigation_params)
    response      [line]                exposure factor vs the calibration (1 ms at 0 dB if none)
    navigation    [nav_sample, 7]       raw .lcf samples of all cubes: time, roll, pitch, yaw, lon, lat, alt
    navigation_offset [cube + 1]        rows of cube k are navigation[offset[k]:offset[k+1]]
    navigation_use [nav_sample]         1 = use, 0 = flagged 'do not use' (.lcf column 10); only when some row is
    wavelength    [band]                nm (NaN when the header has none)
    fwhm          [band]                spectral full width at half maximum, nm (NaN when the header has
                  none; absent in stores ingested before it was recorded)
    dark          [cube, band, sample]  calibration dark of each cube, float32 (only with a calibration)
    gain          [set, band, sample]   calibration gain, float32; cube k uses gain[gain_index[k]]
    gain_index    [cube]
    downwelling   [cube, band]          the sky spectrometer's X per cube on the camera's bands (microflicks:
                  a white panel's radiance; only for flights with downwelling spectra, issue 34); the
                  attribute ``downwelling`` names the spectra and the .dcp (also in ``sources``, hashed)

Group attributes hold the id, software version, field of view, ground height, the local frame,
every cube's full header metadata, the source files (name, size, sha256), calibration reference
exposure, sha256 of every small array, and LAST ``"archive:complete": true``.
Every dimension name means one length, so ``xarray.open_zarr(store, consolidated=False)`` opens a
collection as it is (stores ingested before 2026-11-24 named navigation's rows 'sample' too: open
those with ``drop_variables=["navigation", "navigation_use"]``). Nothing depends on
the wall clock, so ingesting the same flight twice gives byte-identical stores.

Chunking: Zarr 3 needs a regular chunk grid, so the line chunk length is the most common cube
length (ties: the longest). Flights whose cubes all have that length (the last may be shorter)
get exactly one chunk per band per cube; otherwise a cube's lines may span two chunks and each
write task assembles its chunk from the cubes it overlaps, so that every task still writes whole
chunks (concurrent partial writes into one chunk lose updates). Sharding would not help: shards
are regular too, and per-band tasks would then share shards.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from archive import storage
from archive.codecs import numcodecs_blosc
from archive.errors import FormatError, InputError, MissingInputError
from archive.files import FileLock, remove_path, replace_path, test_hold_calls, write_atomic
from archive.formats.envi import EnviCube, EnviHeader, header_from_metadata
from archive.formats.lcf import LcfData
from archive.navigation import LocalFrame

FORMAT = "archive-collection"
FORMAT_VERSION = 1
COMPLETE = "archive:complete"
NAV_COLUMNS = ("time", "roll", "pitch", "yaw", "lon", "lat", "alt")
# Chosen from bench/RESULTS.md "Ingest codec": best ratio on 12-bit DN among fast decoders.
DN_CODEC = {"cname": "zstd", "clevel": 3, "shuffle": "bitshuffle"}
SMALL_CODEC = {"cname": "zstd", "clevel": 5, "shuffle": "shuffle"}


def _blosc(spec: dict) -> BloscCodec:
    return BloscCodec(cname=spec["cname"], clevel=spec["clevel"], shuffle=spec["shuffle"])


def _loc(store: str | os.PathLike):
    """A store location as a path object: :class:`pathlib.Path`, or a UPath for an ``s3://`` URL."""
    return storage.location(store) if storage.is_url(store) else Path(store)


def _zarr(store, read_only: bool = True):
    """What zarr opens for the store ``store`` (the path itself, or an obstore ObjectStore for a URL)."""
    return storage.zarr_store(store, read_only=read_only) if storage.is_url(store) else store


def _zarr_json(store) -> dict:
    """The parsed root ``zarr.json`` of a store (OSError / ValueError when absent or unreadable)."""
    return json.loads(storage.read_bytes(_loc(store) / "zarr.json"))


def is_complete(store: str | os.PathLike) -> bool:
    """Whether ``store`` is a collection whose completion marker was written (reads only zarr.json)."""
    try:
        meta = _zarr_json(store)
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and (meta.get("attributes") or {}).get(COMPLETE) is True


def sha256_file(path: str | os.PathLike, block: int = 1 << 22) -> str:
    """Hex sha256 of a file, read in 4 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def chunk_digest(data: np.ndarray) -> bytes:
    """sha256 of an array's bytes in C order, little endian (the recorded chunk checksum)."""
    a = np.ascontiguousarray(data)
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
    return hashlib.sha256(a.reshape(-1).view(np.uint8).data).digest()   # no copy of the bytes


def array_digest(data: np.ndarray) -> str:
    return chunk_digest(np.asarray(data)).hex() + f":{np.asarray(data).dtype.str}:{list(np.shape(data))}"


def chunk_lines_for(cube_lines: Sequence[int]) -> int:
    """Line chunk length: the most common cube length, ties broken by the longest."""
    counts = Counter(int(n) for n in cube_lines)
    return max(counts, key=lambda n: (counts[n], n))


@dataclass(frozen=True)
class ChunkTask:
    """One dn chunk: band ``band``, lines [line0, line1) of the collection, assembled from
    ``pieces`` = ((data file, first cube line, end cube line), ...) in order."""

    band: int
    chunk: int
    line0: int
    line1: int
    pieces: tuple[tuple[str, int, int], ...]


def chunk_tasks(data_files: Sequence[str], cube_lines: Sequence[int], bands: int, chunk_lines: int) -> list[ChunkTask]:
    """Every (band, chunk) of a flight, band-major, and the cube line ranges that fill it."""
    offsets = np.concatenate([[0], np.cumsum(cube_lines)]).astype(int)
    total = int(offsets[-1])
    layout = []
    for k, l0 in enumerate(range(0, total, chunk_lines)):
        l1 = min(l0 + chunk_lines, total)
        pieces = []
        for c, path in enumerate(data_files):
            a, b = max(l0, offsets[c]), min(l1, offsets[c + 1])
            if a < b:
                pieces.append((str(path), int(a - offsets[c]), int(b - offsets[c])))
        layout.append((k, l0, l1, tuple(pieces)))
    return [ChunkTask(b, k, l0, l1, pieces) for b in range(bands) for k, l0, l1, pieces in layout]


def chunk_path(store: Path, band: int, chunk: int) -> Path:
    """File (or object, for a URL) of dn chunk (band, chunk) in a Zarr v3 store (default '/' chunk key encoding)."""
    return _loc(store) / "dn" / "c" / str(band) / str(chunk) / "0"


@lru_cache(maxsize=64)
def _cube(path: str, size: int, mtime_ns: int) -> EnviCube:
    return EnviCube(path)


#: Test-only: ``ARCHIVE_TEST_HOLD_AFTER_CHUNKS=N`` makes an ingest stop (its chunk tasks wait until
#: the process is killed) once its store holds N dn chunks (kept from a resumed run or written), so
#: that a test kills it mid-store at a moment it controls (never set outside tests).
TEST_HOLD_AFTER_CHUNKS = "ARCHIVE_TEST_HOLD_AFTER_CHUNKS"
def write_chunk(store: str, task: ChunkTask, chunk_lines: int, resume: bool) -> tuple[int, int, str]:
    """Dask task body: read one band of the raw cubes for ``task``, write it as one dn chunk, and
    return (band, chunk, hex sha256 of the chunk's values).

    The chunk is encoded here with the store's codec (bytes little endian + Blosc, the same bytes
    zarr writes, checked by the tests) and written under a temporary name then renamed, which runs
    the compression in this worker thread instead of zarr's event loop. An edge chunk is padded
    with the fill value 0 to ``chunk_lines`` lines, as Zarr stores it. With ``resume``, a chunk
    already on disk that decodes to the same values is kept. Memory: one chunk and its encoding.
    """
    test_hold_calls(TEST_HOLD_AFTER_CHUNKS)
    parts = []
    for path, a, b in task.pieces:
        st = os.stat(path)
        parts.append(_cube(path, st.st_size, st.st_mtime_ns).band(task.band)[a:b])
    data = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)
    data = np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("<"))
    digest = chunk_digest(data)
    codec = numcodecs_blosc(DN_CODEC["cname"], DN_CODEC["clevel"], DN_CODEC["shuffle"])
    target = chunk_path(_loc(store), task.band, task.chunk)
    url = storage.is_url(store)
    if resume and (url or target.is_file()):
        try:
            old = np.frombuffer(codec.decode(storage.read_bytes(target)), data.dtype)
            if chunk_digest(old[: data.size]) == digest:
                return task.band, task.chunk, digest.hex()
        except Exception:  # noqa: BLE001 - a damaged chunk from a killed run is simply rewritten
            pass
    if data.shape[0] < chunk_lines:
        padded = np.zeros((chunk_lines, data.shape[1]), data.dtype)
        padded[: data.shape[0]] = data
        data = padded
    if url:   # one PUT, straight from this worker (no staging): atomic per object
        storage.write_bytes(target, codec.encode(data))
        return task.band, task.chunk, digest.hex()
    target.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(target, codec.encode(data))
    return task.band, task.chunk, digest.hex()


def hash_file_task(path: str) -> tuple[str, str]:
    """Dask task body: (path, hex sha256)."""
    return path, sha256_file(path)


# ----------------------------------------------------------------------------------------------
# writing


@dataclass
class StorePlan:
    """Everything an ingest writes, prepared in memory before the archive is touched.

    arrays: small arrays by name; attrs: group attributes (without checksums and the marker);
    data_files: the cubes' data files in capture order; cube_lines, bands, samples, dtype: dn shape
    and type; sources: (path, size) of every raw file whose sha256 is recorded.
    """

    cid: str
    arrays: dict[str, np.ndarray]
    attrs: dict
    data_files: list[str]
    cube_lines: list[int]
    bands: int
    samples: int
    dtype: np.dtype
    sources: list[tuple[str, int]]
    dims: dict[str, tuple[str, ...]] = field(default_factory=dict)

    @property
    def chunk_lines(self) -> int:
        return chunk_lines_for(self.cube_lines)

    def token(self) -> str:
        """Identifies what is being written (sources, shapes, parameters, the small arrays' names: a
        partial store laid out by an older version without some array is not resumed), to resume safely."""
        text = json.dumps([self.cid, self.sources, self.cube_lines, self.bands, self.samples, self.dtype.str,
                           self.attrs.get("fov_deg"), self.attrs.get("ground_height"), DN_CODEC,
                           self.attrs.get("navigation_params"), sorted(self.arrays)], default=str)
        return hashlib.sha256(text.encode()).hexdigest()


def _create_arrays(store: Path, plan: StorePlan) -> None:
    # "w-", not "w": the store is new (open_partial removed any old one), and "w" makes zarr clear it,
    # which for a local store removes the folder it has just created and makes it again; a SIGKILL
    # in between left no partial store at all (seen once in CI: tests/test_collection.py's SIGKILL test)
    group = zarr.open_group(_zarr(store, read_only=False), mode="w-", zarr_format=3)
    total = sum(plan.cube_lines)
    group.create_array(
        "dn", shape=(plan.bands, total, plan.samples), chunks=(1, plan.chunk_lines, plan.samples),
        dtype=plan.dtype, compressors=[_blosc(DN_CODEC)], fill_value=0,
        dimension_names=("band", "line", "sample"), config={"write_empty_chunks": True})
    for name, values in plan.arrays.items():
        a = group.create_array(name, shape=values.shape, chunks=values.shape or (1,), dtype=values.dtype,
                               compressors=[_blosc(SMALL_CODEC)], fill_value=0,
                               dimension_names=plan.dims.get(name), config={"write_empty_chunks": True})
        a[...] = values


def _clean_stray_temporaries(store: Path) -> None:
    # zarr's LocalStore writes '<key>.<uuid>.partial' then renames; a SIGKILL can leave them.
    for p in store.rglob("*.partial"):
        if p.is_file():
            p.unlink()


def open_partial(partial: Path, plan: StorePlan) -> bool:
    """Prepare ``partial`` for writing ``plan``: reuse it when an earlier run of the same plan left
    it (returns True: resume), else create it afresh (returns False). For a URL, ``partial`` is the
    store's final prefix (S3 has no rename): its ``zarr.json`` says complete only once finished."""
    token = plan.token()
    url = storage.is_url(partial)
    if partial.exists():
        try:
            attrs = _zarr_json(partial).get("attributes", {})
        except (OSError, ValueError):
            attrs = {}
        if attrs.get("archive:plan") == token and not (url and attrs.get(COMPLETE) is True):
            if not url:
                _clean_stray_temporaries(partial)
            return True
        if url:
            storage.delete(partial / "zarr.json")   # first: the old store stops being complete
            storage.delete_prefix(partial)
        else:
            shutil.rmtree(partial)
    if not url:
        partial.parent.mkdir(parents=True, exist_ok=True)
    _create_arrays(partial, plan)
    # Written after every array exists: a partial store carrying this token is fully laid out.
    group = zarr.open_group(_zarr(partial, read_only=False), mode="r+")
    group.attrs.put({"archive:plan": token})
    return False


def finish_store(partial: Path, plan: StorePlan, chunk_digests: dict[tuple[int, int], str],
                 file_digests: dict[str, str]) -> None:
    """Record checksums and metadata, then the completion marker (last write)."""
    nchunks = -(-sum(plan.cube_lines) // plan.chunk_lines)
    table = np.zeros((plan.bands, nchunks, 32), np.uint8)
    for (b, k), hexd in chunk_digests.items():
        table[b, k] = np.frombuffer(bytes.fromhex(hexd), np.uint8)
    group = zarr.open_group(_zarr(partial, read_only=False), mode="r+")
    a = group.create_array("dn_sha256", shape=table.shape, chunks=table.shape, dtype=np.uint8,
                           compressors=[_blosc(SMALL_CODEC)], fill_value=0, overwrite=True,
                           dimension_names=("band", "chunk", "byte"), config={"write_empty_chunks": True})
    a[...] = table
    attrs = dict(plan.attrs)
    attrs["sources"] = [{"name": attrs["source_names"][path], "size": size, "sha256": file_digests[path]}
                        for path, size in plan.sources]
    del attrs["source_names"]
    attrs["array_sha256"] = {name: array_digest(v) for name, v in sorted(plan.arrays.items())}
    attrs["archive:plan"] = plan.token()
    group.attrs.put(attrs)
    group.attrs.put({**attrs, COMPLETE: True})


def record_navigation(store: str | os.PathLike, navigation_params: dict, arrays: dict[str, np.ndarray],
                      ground_height: float | None = None, note: dict | None = None) -> None:
    """Give a complete collection new navigation parameters (``archive calibrate --apply``):
    ``navigation_params`` ('sync_offset', 'boresight_deg', 'lever_arm_m'), the per-line arrays they
    give ('time', 'position', 'attitude': same shapes as stored), optionally a new flat
    ``ground_height`` (m) and a ``note`` kept as the 'navigation_calibration' attribute. The
    completion marker is taken off first and put back last (an interrupted update leaves an
    incomplete store, never a silently inconsistent one); the arrays' checksums follow them. Holds
    the collection's lock (:func:`store_lock`; waits for an ingest of it to finish)."""
    store = _loc(store)
    lock = store_lock(store, f"navigation update of {store.name.removesuffix('.zarr')}")
    lock.acquire(wait=float("inf"))
    try:
        _record_navigation(store, navigation_params, arrays, ground_height, note)
    finally:
        lock.release()


def _record_navigation(store: Path, navigation_params: dict, arrays: dict[str, np.ndarray],
                       ground_height: float | None, note: dict | None) -> None:
    group = zarr.open_group(_zarr(store, read_only=False), mode="r+")
    attrs = dict(group.attrs)
    if attrs.get(COMPLETE) is not True:
        raise InputError(store, "is not a complete collection", "re-ingest it")
    for name, values in arrays.items():
        if name not in ("time", "position", "attitude") or tuple(group[name].shape) != values.shape:
            raise InputError(store, f"array {name} cannot be replaced by shape {values.shape}")
    attrs.pop(COMPLETE)
    group.attrs.put(attrs)
    digests = dict(attrs.get("array_sha256", {}))
    for name, values in arrays.items():
        values = np.asarray(values, group[name].dtype)
        group[name][...] = values
        digests[name] = array_digest(values)
    attrs["array_sha256"] = digests
    attrs["navigation_params"] = {"sync_offset": float(navigation_params["sync_offset"]),
                                  "boresight_deg": [float(v) for v in navigation_params["boresight_deg"]],
                                  "lever_arm_m": [float(v) for v in navigation_params["lever_arm_m"]]}
    if ground_height is not None:
        attrs["ground_height"] = float(ground_height)
        attrs["ground_height_source"] = "archive calibrate"
    if note is not None:
        attrs["navigation_calibration"] = note
    group.attrs.put(attrs)
    group.attrs.put({**attrs, COMPLETE: True})


def store_lock(store: str | os.PathLike, purpose: str) -> FileLock:
    """The exclusive lock of the collection ``store`` (``<id>.zarr.lock`` beside it, not yet taken):
    whoever writes the store (an ingest, its partial store included; ``calibrate --apply``) holds it,
    so that two writers of one id, in two processes or on two hosts, never share a partial store.
    ``purpose`` says what the holder does (shown to whoever waits)."""
    store = _loc(store)
    cid = store.name.removesuffix(".zarr")
    return FileLock(store.with_name(store.name + ".lock"), purpose, what=f"collection {cid}",
                    fix="wait for it to finish")


def publish(partial: Path, final: Path) -> None:
    """Rename the finished partial store to its final name (replacing an older store). In object
    storage the partial store IS the final one (its completion marker, written last, published it)."""
    if storage.is_url(final):
        if str(partial) != str(final):
            raise ValueError(f"{partial}: an object store's partial store must be its final prefix {final}")
        return
    replace_path(partial, final)


# ----------------------------------------------------------------------------------------------
# verifying


def verify_store(store: str | os.PathLike, progress: bool = False) -> list[str]:
    """Recompute the sha256 of every dn chunk and every small array and compare with the recorded
    ones. Returns the problems found (empty: OK)."""
    from tqdm import tqdm

    store = _loc(store)
    if not is_complete(store):
        return [f"{store}: incomplete collection (no completion marker)"]
    group = zarr.open_group(_zarr(store), mode="r")
    attrs = dict(group.attrs)
    problems = []
    for name, expected in sorted(attrs.get("array_sha256", {}).items()):
        try:
            found = array_digest(group[name][...])
        except Exception as exc:  # noqa: BLE001 - report any unreadable array
            problems.append(f"array {name}: unreadable ({type(exc).__name__}: {exc})")
            continue
        if found != expected:
            problems.append(f"array {name}: checksum mismatch")
    dn = group["dn"]
    table = group["dn_sha256"][...]
    chunk = dn.chunks[1]
    bands, total = dn.shape[0], dn.shape[1]
    nchunks = table.shape[1]
    with tqdm(total=bands * nchunks, desc=f"verify {store.name}", unit="chunk", disable=not progress) as bar:
        for b in range(bands):
            for k in range(nchunks):
                where = f"dn chunk (band {b}, lines {k * chunk}-{min((k + 1) * chunk, total) - 1})"
                if not storage.exists(chunk_path(store, b, k)):
                    problems.append(f"{where}: missing")
                else:
                    try:
                        if chunk_digest(dn[b, k * chunk:(k + 1) * chunk]) != table[b, k].tobytes():
                            problems.append(f"{where}: checksum mismatch")
                    except Exception as exc:  # noqa: BLE001 - undecodable chunk
                        problems.append(f"{where}: cannot be decoded ({type(exc).__name__})")
                bar.update(1)
    return problems


# ----------------------------------------------------------------------------------------------
# reading


def frame_to_attrs(frame: LocalFrame) -> dict:
    """The ``frame`` group attribute of a local frame."""
    return {"epsg": int(frame.epsg), "origin_e": float(frame.origin_e), "origin_n": float(frame.origin_n),
            "origin_alt": float(frame.origin_alt)}


def frame_from_attrs(f: dict) -> LocalFrame:
    """The local frame recorded in a ``frame`` group attribute."""
    return LocalFrame(int(f["epsg"]), float(f["origin_e"]), float(f["origin_n"]), float(f["origin_alt"]))


@dataclass(frozen=True, eq=False)
class StoredCube:
    """One cube as recorded: index, base name, shape, first line in ``dn``, its header (path names
    the store), its camera clock (lines,) s and its raw navigation."""

    index: int
    base: str
    lines: int
    samples: int
    bands: int
    line_offset: int
    header: EnviHeader
    camera_time: np.ndarray
    lcf: LcfData


@dataclass(frozen=True, eq=False)
class CollectionInfo:
    """What a completed collection records, read from its attributes and small arrays (no DN).

    store: the store path; attrs: every group attribute; fov_deg, ground_height (m, .lcf datum):
    as ingested; frame: the local frame; cubes: per cube; calibration: None, or {name,
    shutter_cal, gain_cal}; plan: the plan token (identifies the stored content); fwhm: spectral
    full width at half maximum per band, nm (the ``fwhm`` array; a store without it: the first
    cube's recorded header, else None).
    """

    store: Path
    attrs: dict
    fov_deg: float
    ground_height: float | None
    frame: LocalFrame
    cubes: tuple[StoredCube, ...]
    calibration: dict | None
    plan: str | None
    fwhm: tuple[float, ...] | None = None

    @property
    def sources(self) -> list[dict]:
        """Recorded source files: [{name, size, sha256}, ...]."""
        return list(self.attrs.get("sources", []))


def read_attrs(store: str | os.PathLike) -> dict:
    """Group attributes of a collection store; FormatError unless it is a complete collection this
    software can read."""
    store = _loc(store)
    if not storage.exists(store / "zarr.json"):
        raise MissingInputError(store, "collection store")
    attrs = dict(zarr.open_group(_zarr(store), mode="r").attrs)
    if attrs.get("archive:format") != FORMAT or int(attrs.get("archive:format_version", 0)) > FORMAT_VERSION:
        raise FormatError(store, "not a collection store this software can read",
                          "re-ingest the flight or upgrade archive")
    if attrs.get(COMPLETE) is not True:
        raise FormatError(store, "incomplete collection (no completion marker)", "re-run the ingest")
    return attrs


def content_version(store: str | os.PathLike) -> dict | None:
    """What a render of the collection ``store`` depends on beyond the render's options (reads only
    its ``zarr.json``): ``navigation_params`` (sync offset, boresight, lever arm), ``ground_height``
    and ``fov_deg`` as recorded, and ``version``, the sha256 of everything that identifies its
    content (plan token: sources, shapes, parameters; the raw files' sha256; the small arrays'
    sha256, which ``calibrate --apply`` changes; terrain; calibration). A re-ingest with other
    parameters, or a ``calibrate --apply``, gives another version; ingesting the same flight again
    the same way gives the same (stores are byte-identical). None when it is not a complete
    collection."""
    try:
        meta = _zarr_json(store)
    except (OSError, ValueError):
        return None
    attrs = meta.get("attributes") if isinstance(meta, dict) else None
    if not isinstance(attrs, dict) or attrs.get(COMPLETE) is not True:
        return None
    keys = ("archive:plan", "sources", "array_sha256", "navigation_params", "ground_height", "fov_deg", "terrain",
            "calibration", "frame")
    text = json.dumps({k: attrs.get(k) for k in keys}, sort_keys=True, default=str)
    return {"navigation_params": attrs.get("navigation_params"), "ground_height": attrs.get("ground_height"),
            "fov_deg": attrs.get("fov_deg"), "version": hashlib.sha256(text.encode()).hexdigest()}


def read_info(store: str | os.PathLike, navigation: bool = True) -> CollectionInfo:
    """The recorded description of a collection (see :class:`CollectionInfo`); with ``navigation``
    also every cube's camera clock and raw navigation."""
    store = _loc(store)
    attrs = read_attrs(store)
    group = zarr.open_group(_zarr(store), mode="r")
    nav = group["navigation"][...] if navigation else None
    offsets = group["navigation_offset"][...] if navigation else None
    camera_time = group["camera_time"][...] if navigation else None
    use = group["navigation_use"][...].astype(bool) if navigation and "navigation_use" in group else None
    cubes = []
    for k, c in enumerate(attrs["cubes"]):
        header = header_from_metadata(c["header"], store / f"{c['base']}.hdr")
        l0 = int(c["line_offset"])
        if navigation:
            rows = nav[int(offsets[k]):int(offsets[k + 1])]
            used = None if use is None else use[int(offsets[k]):int(offsets[k + 1])]
            lcf = LcfData(None, *(np.ascontiguousarray(rows[:, j]) for j in range(len(NAV_COLUMNS))),
                          use=None if used is None or used.all() else used)
            times = np.ascontiguousarray(camera_time[l0:l0 + int(c["lines"])])
        else:
            lcf = times = None
        cubes.append(StoredCube(k, c["base"], int(c["lines"]), int(c["samples"]), int(c["bands"]), l0, header,
                                times, lcf))
    ground = attrs.get("ground_height")
    fwhm = _band_values(group, "fwhm") if "fwhm" in group else (cubes[0].header.fwhm if cubes else None)
    return CollectionInfo(store, attrs, float(attrs["fov_deg"]), None if ground is None else float(ground),
                          frame_from_attrs(attrs["frame"]), tuple(cubes), attrs.get("calibration"),
                          attrs.get("archive:plan"), None if fwhm is None else tuple(fwhm))


def _band_values(group, name: str) -> list[float] | None:
    """A stored per-band array (``wavelength``, ``fwhm``; nm) as floats; None when absent or all NaN."""
    if name not in group:
        return None
    values = group[name][...]
    return None if np.all(np.isnan(values)) else [float(v) for v in values]


@dataclass(frozen=True, eq=False)
class StoredPoses:
    """The per-line record of a collection: time (lines,) s on the .lcf scale; position (lines, 3)
    camera N, E, D metres and attitude (lines,) camera -> NED, both at exposure start with the
    ingest's navigation parameters; shape (bands, lines, samples) of ``dn``; wavelengths (bands,)
    nm or None; fwhm (bands,) spectral full width at half maximum, nm, or None (also for stores
    ingested before it was recorded)."""

    time: np.ndarray
    position: np.ndarray
    attitude: object
    shape: tuple[int, int, int]
    wavelengths: list[float] | None
    fwhm: list[float] | None = None


def read_poses(store: str | os.PathLike) -> StoredPoses:
    """The stored per-line times and poses, the dn shape, the wavelengths and fwhm (no DN read)."""
    from scipy.spatial.transform import Rotation

    group = zarr.open_group(_zarr(store), mode="r")
    return StoredPoses(group["time"][...], group["position"][...], Rotation.from_quat(group["attitude"][...]),
                       tuple(int(v) for v in group["dn"].shape), _band_values(group, "wavelength"),
                       _band_values(group, "fwhm"))


def read_downwelling(store: str | os.PathLike) -> np.ndarray | None:
    """(cubes, bands) stored downwelling X (microflicks) of a collection, None when it has none."""
    group = zarr.open_group(_zarr(store), mode="r")
    if "downwelling" not in group:
        return None
    x = np.asarray(group["downwelling"][...], np.float64)
    digest = (group.attrs.get("array_sha256") or {}).get("downwelling")
    if digest is not None and array_digest(x) != digest:
        raise CorruptChunkError(store, "array 'downwelling' does not match its recorded sha256",
                                "run `archive verify` and re-ingest the flight")
    return x


class StoredCalibration:
    """The calibration arrays of a collection (``dark`` [cube, band, sample], ``gain`` [set, band,
    sample], ``gain_index`` [cube]), opened once: each :meth:`read` then reads only the two rows it
    needs (opening the group costs more than reading a row: a reader of many cubes keeps one)."""

    def __init__(self, store: str | os.PathLike):
        group = zarr.open_group(_zarr(store), mode="r")
        self.dark, self.gain = group["dark"], group["gain"]
        self.gain_index = np.asarray(group["gain_index"][...])

    def read(self, cube: int, bands: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Stored dark and gain of ``bands`` of ``cube``: each (len(bands), samples) float32."""
        dark = self.dark[cube]
        gain = self.gain[int(self.gain_index[cube])]
        return dark[list(bands)], gain[list(bands)]


def open_dn(store: str | os.PathLike):
    """The stored ``dn`` array (band, line, sample), read-only, unchecked (:class:`CheckedDn` checks)."""
    return zarr.open_array(_zarr(store), path="dn", mode="r")


class CorruptChunkError(FormatError):
    """A dn chunk of a collection does not decode, is missing, or does not match its recorded sha256."""


class CheckedDn:
    """The ``dn`` array of a collection, read whole chunk by whole chunk, each chunk's decoded values
    checked against the sha256 recorded at ingest (``dn_sha256``) before any of them is used: a
    flipped byte that the codec still decodes, a truncated or missing chunk file is a
    :class:`CorruptChunkError` naming the collection, band and lines. Every reader of DN (renders,
    :func:`archive.mosaic`, the viewer) goes through this (via the collection source)."""

    def __init__(self, store: str | os.PathLike):
        self.store = _loc(store)
        group = zarr.open_group(_zarr(self.store), mode="r")
        self.array = group["dn"]
        if "dn_sha256" not in group:
            raise CorruptChunkError(self.store, "collection has no dn chunk checksums (dn_sha256)",
                                    self._fix())
        self.digests = np.asarray(group["dn_sha256"][...])
        self.chunk = int(self.array.chunks[1])
        self.dtype = self.array.dtype

    def _fix(self) -> str:
        archive, cid = self.store.parent.parent, self.store.name.removesuffix(".zarr")
        return (f"run 'archive verify --archive {archive} {cid}', then re-ingest the flight from its raw files "
                f"with 'archive ingest RAW_DIR --archive {archive} --overwrite'")

    def _fail(self, band: int, line0: int, line1: int, problem: str) -> CorruptChunkError:
        cid = self.store.name.removesuffix(".zarr")
        return CorruptChunkError(self.store, f"collection {cid}: array dn, band {band}, lines {line0}-{line1 - 1}: "
                                 f"{problem}", self._fix())

    def read(self, band: int, line0: int, line1: int) -> np.ndarray:
        """(line1 - line0, samples) DN of ``band``, lines [line0, line1), every chunk they touch checked."""
        total, c = int(self.array.shape[1]), self.chunk
        out = np.empty((line1 - line0, int(self.array.shape[2])), self.dtype)
        k0, k1 = line0 // c, -(-line1 // c)
        whole = None
        if storage.is_url(self.store) and k1 - k0 > 1:
            # object storage: every chunk of the range in one zarr call (its requests run
            # concurrently), then each chunk checked; a failure re-reads chunk by chunk to name it
            try:
                whole = self.array[band, k0 * c:min(k1 * c, total)]
            except Exception:  # noqa: BLE001 - found again, by chunk, below
                whole = None
        for k in range(k0, k1):
            a, b = k * c, min((k + 1) * c, total)
            try:
                values = self.array[band, a:b] if whole is None else whole[a - k0 * c:b - k0 * c]
            except Exception as exc:  # noqa: BLE001 - any decoding failure of the stored bytes
                why = storage.reason(exc)   # the bucket unreachable is not a damaged chunk
                if why is not None:
                    raise storage.StorageError(chunk_path(self.store, band, k), why) from None
                raise self._fail(band, a, b, f"chunk cannot be decoded ({type(exc).__name__}: {exc})") from None
            if chunk_digest(values) != self.digests[band, k].tobytes():
                missing = not storage.exists(chunk_path(self.store, band, k))
                raise self._fail(band, a, b, "chunk file is missing" if missing else
                                 "chunk does not match its recorded sha256 (the stored bytes changed)")
            lo, hi = max(a, line0), min(b, line1)
            out[lo - line0:hi - line0] = values[lo - a:hi - a]
        return out

    def read_bands(self, bands: Sequence[int], line0: int, line1: int) -> np.ndarray:
        """(len(bands), line1 - line0, samples) DN of ``bands``, lines [line0, line1), every chunk
        checked as by :meth:`read`. In object storage every chunk of the block is fetched in one
        zarr call (its requests run concurrently: one request's latency instead of one per band),
        then each checked; on a local disk, :meth:`read` band by band (the same values)."""
        bands = [int(b) for b in bands]
        total, c = int(self.array.shape[1]), self.chunk
        if storage.is_url(self.store) and len(bands) > 1:
            k0, k1 = line0 // c, -(-line1 // c)
            a0, a1 = k0 * c, min(k1 * c, total)
            try:
                block = self.array.get_orthogonal_selection((bands, slice(a0, a1), slice(None)))
            except Exception:  # noqa: BLE001 - found again, and named, by read() below
                block = None
            if block is not None and all(
                    chunk_digest(block[i, k * c - a0:min((k + 1) * c, total) - a0]) == self.digests[b, k].tobytes()
                    for i, b in enumerate(bands) for k in range(k0, k1)):
                return np.ascontiguousarray(block[:, line0 - a0:line1 - a0])
        out = np.empty((len(bands), line1 - line0, int(self.array.shape[2])), self.dtype)
        for i, b in enumerate(bands):
            out[i] = self.read(b, line0, line1)
        return out


__all__ = ["COMPLETE", "CheckedDn", "CollectionInfo", "CorruptChunkError", "FORMAT", "FORMAT_VERSION", "NAV_COLUMNS",
           "StorePlan", "StoredCalibration", "StoredCube", "StoredPoses", "chunk_tasks", "content_version",
           "finish_store", "frame_from_attrs", "frame_to_attrs", "is_complete", "open_dn", "open_partial", "publish",
           "read_attrs", "read_info", "read_poses", "record_navigation", "store_lock", "verify_store", "write_chunk"]
