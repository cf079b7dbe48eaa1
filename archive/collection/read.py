"""Reading a collection: its attributes, the recorded description, poses, calibration and
downwelling arrays, and the dn array checked chunk by chunk against its recorded digests."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import zarr

from archive import storage
from archive.collection.update import settle
from archive.collection.layout import (COMPLETE, FORMAT, FORMAT_VERSION, NAV_COLUMNS, array_digest, chunk_digest,
                                       chunk_path, digest_table, dn_checksum, location, root_json, zarr_target)
from archive.errors import FormatError, InputError, MissingInputError
from archive.formats.envi import EnviHeader, header_from_metadata
from archive.formats.lcf import LcfData
from archive.geometry.navigation import LocalFrame

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
    store = location(store)
    settle(store)   # an update (calibrate --apply) a kill interrupted is finished first
    if not storage.exists(store / "zarr.json"):
        raise MissingInputError(store, "collection store")
    attrs = dict(zarr.open_group(zarr_target(store), mode="r").attrs)
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
        meta = root_json(store)
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
    store = location(store)
    attrs = read_attrs(store)
    group = zarr.open_group(zarr_target(store), mode="r")
    nav = checked_array(store, group, "navigation", attrs) if navigation else None
    offsets = checked_array(store, group, "navigation_offset", attrs) if navigation else None
    camera_time = checked_array(store, group, "camera_time", attrs) if navigation else None
    use = checked_array(store, group, "navigation_use", attrs).astype(bool) \
        if navigation and "navigation_use" in group else None
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
    fwhm = _band_values(group, "fwhm", store) if "fwhm" in group else (cubes[0].header.fwhm if cubes else None)
    return CollectionInfo(store, attrs, float(attrs["fov_deg"]), None if ground is None else float(ground),
                          frame_from_attrs(attrs["frame"]), tuple(cubes), attrs.get("calibration"),
                          attrs.get("archive:plan"), None if fwhm is None else tuple(fwhm))


def _fix(store) -> str:
    store = location(store)
    archive, cid = store.parent.parent, store.name.removesuffix(".zarr")
    return (f"run 'archive verify --archive {archive} {cid}', then re-ingest the flight from its raw files "
            f"with 'archive ingest RAW_DIR --archive {archive} --overwrite'")


def checked_array(store, group, name: str, attrs: dict | None = None) -> np.ndarray:
    """The whole small array ``name`` of the collection ``store`` (its open zarr ``group``; ``attrs``
    its attributes), checked against the sha256 recorded for it (``array_sha256``) before any value is
    used: :class:`CorruptChunkError` naming the collection and the array when it does not decode or
    does not match (an array recorded without a digest is returned as it is)."""
    cid = location(store).name.removesuffix(".zarr")
    attrs = dict(group.attrs) if attrs is None else attrs
    try:
        values = group[name][...]
    except Exception as exc:  # noqa: BLE001 - any decoding failure of the stored bytes
        why = storage.reason(exc)   # the bucket unreachable is not a damaged array
        if why is not None:
            raise storage.StorageError(location(store) / name, why) from None
        raise CorruptChunkError(store, f"collection {cid}: array {name} cannot be decoded ({type(exc).__name__}: "
                                f"{' '.join(str(exc).split())})", _fix(store)) from None
    digest = (attrs.get("array_sha256") or {}).get(name)
    if digest is not None and array_digest(values) != digest:
        raise CorruptChunkError(store, f"collection {cid}: array {name} does not match its recorded sha256 (the "
                                "stored bytes changed)", _fix(store))
    return values


def _band_values(group, name: str, store=None) -> list[float] | None:
    """A stored per-band array (``wavelength``, ``fwhm``; nm) as floats, checked against its digest
    when ``store`` is given; None when absent or all NaN."""
    if name not in group:
        return None
    values = group[name][...] if store is None else checked_array(store, group, name)
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

    group = zarr.open_group(zarr_target(store), mode="r")
    attrs = dict(group.attrs)
    t, p, q = (checked_array(store, group, name, attrs) for name in ("time", "position", "attitude"))
    return StoredPoses(t, p, Rotation.from_quat(q),
                       tuple(int(v) for v in group["dn"].shape), _band_values(group, "wavelength", store),
                       _band_values(group, "fwhm", store))


def read_downwelling(store: str | os.PathLike) -> np.ndarray | None:
    """(cubes, bands) stored downwelling X (microflicks) of a collection, None when it has none."""
    group = zarr.open_group(zarr_target(store), mode="r")
    if "downwelling" not in group:
        return None
    return np.asarray(checked_array(store, group, "downwelling"), np.float64)


def read_track(store: str | os.PathLike, name: str) -> np.ndarray:
    """(epochs, 7) the post-processed trajectory ``name`` an ingest stored (``track_<name>``: time on the
    ``.lcf`` scale, roll (``.lcf`` sign), pitch, yaw from true north (rad), lon, lat (deg), height (m)),
    checked against its digest. InputError naming the collection's tracks when it has no such one."""
    group = zarr.open_group(zarr_target(store), mode="r")
    tracks = (dict(group.attrs).get("navigation_tracks") or {}).get("tracks") or {}
    if name not in tracks or f"track_{name}" not in group:
        cid = location(store).name.removesuffix(".zarr")
        raise InputError("--navigation", f"collection {cid} has no navigation source {name!r} (it has: "
                         f"{', '.join(['lcf', *tracks])})", "pass --navigation lcf or one of its tracks")
    return np.asarray(checked_array(store, group, f"track_{name}"), float)


class StoredCalibration:
    """The calibration arrays of a collection (``dark`` [cube, band, sample], ``gain`` [set, band,
    sample], ``gain_index`` [cube]), read whole and checked against their digests once per process for
    the same recorded digests (:func:`_checked_calibration`: every render task unpickles its own source
    and makes one of these; reading and hashing a paper flight's dark each time cost ~26 ms a task)."""

    def __init__(self, store: str | os.PathLike):
        digests = dict(zarr.open_group(zarr_target(store), mode="r").attrs).get("array_sha256") or {}
        self.dark, self.gain, self.gain_index = _checked_calibration(
            str(store), *(digests.get(n) for n in ("dark", "gain", "gain_index")))

    def read(self, cube: int, bands: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Stored dark and gain of ``bands`` of ``cube``: each (len(bands), samples) float32."""
        dark = self.dark[cube]
        gain = self.gain[int(self.gain_index[cube])]
        return dark[list(bands)], gain[list(bands)]


@lru_cache(maxsize=2)
def _checked_calibration(store: str, *digests: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dark, gain, gain_index) of the collection ``store``, each checked (:func:`checked_array`); cached by
    the store and the digests its attributes record (``digests``: a re-ingest or another store misses)."""
    group = zarr.open_group(zarr_target(location(store)), mode="r")
    attrs = dict(group.attrs)
    return tuple(np.asarray(checked_array(location(store), group, n, attrs)) for n in ("dark", "gain", "gain_index"))


def open_dn(store: str | os.PathLike):
    """The stored ``dn`` array (band, line, sample), read-only, unchecked (:class:`CheckedDn` checks)."""
    return zarr.open_array(zarr_target(store), path="dn", mode="r")


class CorruptChunkError(FormatError):
    """A dn chunk of a collection does not decode, is missing, or does not match its recorded sha256."""


class CheckedDn:
    """The ``dn`` array of a collection, read whole chunk by whole chunk, each chunk's decoded values
    checked against the digest recorded at ingest (``dn_blake3``, or ``dn_sha256`` in stores of format 1
    and those ingested with ``--checksum sha256``: the algorithm the store records) before any of them is used: a
    flipped byte that the codec still decodes, a truncated or missing chunk file is a
    :class:`CorruptChunkError` naming the collection, band and lines. Every reader of DN (renders,
    :func:`archive.mosaic`, the viewer) goes through this (via the collection source)."""

    def __init__(self, store: str | os.PathLike):
        self.store = location(store)
        group = zarr.open_group(zarr_target(self.store), mode="r")
        self.array = group["dn"]
        #: the algorithm of the recorded chunk digests (:data:`archive.collection.layout.CHECKSUMS`)
        self.checksum = dn_checksum(dict(group.attrs))
        table = digest_table(self.checksum)
        if table not in group:
            raise CorruptChunkError(self.store, f"collection has no dn chunk checksums ({table})",
                                    self._fix())
        self.digests = np.asarray(group[table][...])
        self.chunk = int(self.array.chunks[1])
        self.dtype = self.array.dtype

    def _fix(self) -> str:
        return _fix(self.store)

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
            if chunk_digest(values, self.checksum) != self.digests[band, k].tobytes():
                missing = not storage.exists(chunk_path(self.store, band, k))
                raise self._fail(band, a, b, "chunk file is missing" if missing else
                                 f"chunk does not match its recorded {self.checksum} (the stored bytes changed)")
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
                    chunk_digest(block[i, k * c - a0:min((k + 1) * c, total) - a0], self.checksum)
                    == self.digests[b, k].tobytes()
                    for i, b in enumerate(bands) for k in range(k0, k1)):
                return np.ascontiguousarray(block[:, line0 - a0:line1 - a0])
        out = np.empty((len(bands), line1 - line0, int(self.array.shape[2])), self.dtype)
        for i, b in enumerate(bands):
            out[i] = self.read(b, line0, line1)
        return out
