"""The time stack as an output format: one Zarr store whose data variable is (time, band, y, x),
one time step per flight (see :mod:`archive.run.stacks` for how a stack is rendered and resumed).

This module owns the store's layout: the arrays besides the slices (:class:`StackLayout`), the chunk
files of a step (``chunk_file``: v2 '.'-separated keys, v3 'c/'-prefixed), the step's slice moved in
(:func:`add_slice`), the metadata rewritten with one more step (:func:`commit_stack`: every array's
documents and, Zarr v2, the band names GDAL shows (:mod:`archive.outputs.pam`) first, the consolidated
metadata last, each file replaced atomically), and reading a stack
back (:func:`read_stack`, used by resumes and the viewer).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from archive.errors import InputError
from archive.files import host_name, path_exists, remove_path
from archive.grid import Grid

__all__ = ["STACK_ATTR", "TIME_UNITS", "StackFlight", "StackLayout", "add_slice", "chunk_file", "commit_stack",
           "read_stack"]

#: Root attribute of a stack store: {"flights": [per time step: id, start, end, ...], "request": {...}}.
STACK_ATTR = "archive_stack"
#: CF units of the ``time`` coordinate (int64).
TIME_UNITS = "microseconds since 1970-01-01T00:00:00"

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


@dataclass(frozen=True)
class StackFlight:
    """One time step of a stack: the flight's ``id`` (collection id or directory name), its ``source``
    (what the request names), UTC ``start``/``end`` of its lines (ISO 8601) and its processing
    attributes (ground height or DEM, sync offset, cubes)."""

    id: str
    source: str
    start: str
    end: str
    attrs: dict = dataclasses.field(default_factory=dict, compare=False)

    def to_dict(self) -> dict:
        return {"id": self.id, "source": self.source, "start": self.start, "end": self.end, **self.attrs}

    @classmethod
    def from_dict(cls, d: dict) -> StackFlight:
        rest = {k: v for k, v in d.items() if k not in ("id", "source", "start", "end")}
        return cls(str(d["id"]), str(d.get("source", d["id"])), str(d["start"]), str(d["end"]), rest)

    @property
    def microseconds(self) -> int:
        """The flight's start as CF time: microseconds since 1970-01-01 UTC."""
        when = datetime.fromisoformat(self.start.replace("Z", "+00:00"))
        delta = when - _EPOCH
        return (delta.days * 86400 + delta.seconds) * 1_000_000 + delta.microseconds



@dataclass
class StackLayout:
    """What a stack store holds besides its slices: the grid, the bands (source indices,
    wavelengths, fwhm, nm), the data variable, the root attributes and the Zarr version; ``names``:
    each band's name (a stack of index bands: the indices, bands 0.., no wavelengths)."""

    grid: Grid
    bands: tuple[int, ...]
    wavelengths: tuple[float, ...] | None
    fwhm: tuple[float, ...] | None
    variable: str
    attrs: dict
    zarr_format: int
    names: tuple[str, ...] | None = None

    def arrays(self, flights: Sequence[StackFlight]) -> tuple[dict, list]:
        """(root attributes, :class:`~archive.outputs.zarr_metadata.ArraySpec` list) of the store
        holding ``flights`` as its time steps (no slice data: only the coordinates')."""
        from archive.outputs.zarr import store_layout
        from archive.outputs.zarr_metadata import ArraySpec

        root, arrays = store_layout(self.grid, self.bands, self.wavelengths, self.fwhm, self.variable, self.attrs,
                                    names=self.names)
        n = len(flights)
        out = []
        for spec in arrays:
            if spec.name in (self.variable, "saturated"):
                attrs = dict(spec.attrs)
                attrs["coordinates"] = " ".join(sorted(attrs.get("coordinates", "").split() + ["flight"]))
                spec = dataclasses.replace(spec, shape=(n, *spec.shape), chunks=(1, *spec.chunks),
                                           dims=("time", *spec.dims), attrs=attrs)
            out.append(spec)
        ids = [f.id for f in flights]
        width = max([len(i) for i in ids] + [1])
        out.append(ArraySpec("time", np.dtype(np.int64), (n,), (n,), ("time",),
                             {"units": TIME_UNITS, "calendar": "proleptic_gregorian", "standard_name": "time",
                              "long_name": "start of the flight (its first line), UTC", "axis": "T"},
                             data=np.array([f.microseconds for f in flights], np.int64)))
        out.append(ArraySpec("flight", np.dtype(f"<U{width}"), (n,), (n,), ("time",),
                             {"long_name": "flight (collection id) of each time step"},
                             data=np.array(ids, dtype=f"<U{width}")))
        return dict(root), out


def chunk_file(store: Path, name: str, zarr_format: int, coords: tuple[int, ...]) -> Path:
    """The file of chunk ``coords`` of array ``name`` of a store :mod:`archive.outputs.zarr_metadata`
    wrote (v2: '.'-separated keys; v3: 'c/'-prefixed, '/'-separated)."""
    key = ".".join(str(c) for c in coords) if zarr_format == 2 else "/".join(["c", *(str(c) for c in coords)])
    return store / name / key


def commit_stack(store: Path, layout: StackLayout, flights: list[StackFlight], request: dict) -> None:
    """Rewrite the metadata and coordinates of ``store`` for ``flights`` (its time steps): every
    array's documents and coordinate chunks first, the root documents (consolidated metadata) last,
    each file replaced atomically."""
    from archive.outputs.zarr_metadata import write_store

    root_attrs, arrays = layout.arrays(flights)
    root_attrs[STACK_ATTR] = json.dumps({"variable": layout.variable, "flights": [f.to_dict() for f in flights],
                                         "request": request})
    tmp = store.with_name(f".{store.name}.partial-{os.getpid()}@{host_name()}.meta")
    remove_path(tmp)
    try:
        with warnings.catch_warnings():   # Zarr v3: 'flight' is fixed-length UTF-32, not yet in the v3 spec
            warnings.filterwarnings("ignore", message=".*does not have a Zarr V3 specification.*")
            write_store(tmp, root_attrs, arrays, layout.zarr_format)
        if layout.zarr_format == 2:
            _write_pam(tmp, layout, flights)
        files = sorted(p for p in tmp.rglob("*") if p.is_file())
        late = {".zmetadata", "zarr.json"}
        ordered = ([p for p in files if p.parent != tmp] + [p for p in files if p.parent == tmp and p.name not in late]
                   + [p for p in files if p.parent == tmp and p.name in late])
        for src in ordered:
            dest = store / src.relative_to(tmp)
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dest)
    finally:
        remove_path(tmp)


def _write_pam(store: Path, layout: StackLayout, flights: list[StackFlight]) -> None:
    """The band names GDAL shows for the stack's (time, band, y, x) variable (:mod:`archive.outputs.pam`):
    time-major, band ``t * bands + b + 1`` described as "<wavelength or source band>, <flight id>"
    with the flight's ``flight``, ``time_step`` and ``start`` items beside the band's own."""
    from archive.outputs.base import band_labels
    from archive.outputs.pam import band_texts, write_band_pam

    labels = list(layout.names) if layout.names is not None else band_labels(layout.bands, layout.wavelengths)
    bands = band_texts(labels, layout.wavelengths, layout.fwhm)
    texts = [(f"{label}, {f.id}", {**items, "flight": f.id, "time_step": str(t), "start": f.start}, imagery)
             for t, f in enumerate(flights) for label, items, imagery in bands]
    write_band_pam(store, layout.variable, 4, texts)


def add_slice(slice_store: Path, store: Path, layout: StackLayout, t: int, slice_format: int) -> None:
    """Move the chunk files of a rendered single-flight store (``slice_store``: values (band, y, x)
    and ``saturated`` (y, x)) into time step ``t`` of ``store``; chunks left at ``t`` by a killed
    run are removed first (an all-NaN chunk is not written, so it must not be found there)."""
    g = layout.grid
    rows, cols = math.ceil(g.height / _chunk()), math.ceil(g.width / _chunk())
    for name, nb in ((layout.variable, len(layout.bands)), ("saturated", None)):
        for b in range(nb or 1):
            for r in range(rows):
                for c in range(cols):
                    src_coords = (r, c) if nb is None else (b, r, c)
                    src = chunk_file(slice_store, name, slice_format, src_coords)
                    dest = chunk_file(store, name, layout.zarr_format, (t, *src_coords))
                    if path_exists(dest):
                        remove_path(dest)
                    if src.exists():
                        dest.parent.mkdir(parents=True, exist_ok=True)
                        os.replace(src, dest)


def _chunk() -> int:
    from archive.outputs.base import CHUNK

    return CHUNK


def read_stack(path: str | os.PathLike) -> tuple[StackLayout, list[StackFlight], dict | None]:
    """(layout, flights, request) of an existing stack store; InputError when ``path`` is no stack."""
    import zarr

    from archive.outputs.like import read_grid

    path = Path(path)
    try:
        group = zarr.open_group(path, mode="r")
        attrs = dict(group.attrs)
    except Exception as exc:  # noqa: BLE001 - any unreadable store is the same user error
        raise InputError(path, f"is not a readable Zarr store ({type(exc).__name__})",
                         "pass --overwrite to replace it, or choose another --out") from None
    if STACK_ATTR not in attrs:
        raise InputError(path, "is a Zarr store but not a stack (no archive_stack attribute)",
                         "pass --overwrite to replace it, or choose another --out")
    meta = json.loads(attrs[STACK_ATTR])
    flights = [StackFlight.from_dict(d) for d in meta["flights"]]
    grid = read_grid(path)
    variable = str(meta["variable"])
    wavelengths = tuple(float(v) for v in group["wavelength"][:]) if "wavelength" in group else None
    fwhm = tuple(float(v) for v in group["fwhm"][:]) if "fwhm" in group else None
    bands = tuple(int(v) for v in group["band"][:])
    names = tuple(str(v) for v in group["band_name"][:]) if "band_name" in group else None
    keep = {k: v for k, v in attrs.items() if k not in (STACK_ATTR, "archive_grid", "Conventions", "zarr_conventions")
            and not k.startswith(("proj:", "spatial:"))}
    zarr_format = 2 if (path / ".zgroup").exists() else 3
    return StackLayout(grid, bands, wavelengths, fwhm, variable, keep, zarr_format, names), flights, meta.get("request")

