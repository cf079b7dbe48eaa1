"""The Zarr output's metadata documents, written directly (no xarray, no zarr store round trips).

A mosaic store is created once per output, before any tile is rendered: for a batch of small
flights that creation was most of the client's planning (``xarray.Dataset.to_zarr`` of the
metadata, every array through zarr's event loop: 0.37 of 0.52 s per flight, bench/RESULTS.md
"Batch jobs against the number of flights (issue 19)"). Here the documents (Zarr v2: ``.zgroup``,
``.zattrs``, ``.zarray`` and the consolidated ``.zmetadata``; Zarr v3: ``zarr.json``) are made by
zarr's own metadata classes (so their JSON is zarr's, byte for byte) from an explicit description
of each array (:class:`ArraySpec`: the attributes as xarray's CF encoding writes them), and written
as files, as :class:`archive.outputs.zarr.ChunkWriter` writes chunks. The small coordinate arrays'
chunks are encoded with the arrays' codecs. tests/test_outputs_zarr_metadata.py checks the result
against ``xarray.Dataset.to_zarr`` of :func:`archive.outputs.zarr.mosaic_dataset`.
"""

from __future__ import annotations

import base64
import functools
import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from archive.codecs import numcodecs_blosc

__all__ = ["ArraySpec", "add_arrays", "write_store"]

#: Compressor of the float32 mosaic chunks, both versions (zarr's Blosc codec in v3, the same
#: numcodecs Blosc in v2; also what v2 coordinates get): Blosc LZ4 level 5, byte shuffle. Measured on
#: rendered 1024^2 radiance chunks (25 % NaN; bench/RESULTS.md "Render (issue 4)"): about 560 MB/s to
#: write at ratio 1.7, against 130 MB/s (ratio 2.1) for zarr's default zstd level 0 and 260 MB/s
#: (ratio 1.9) for zstd level 1: writing is on the render's critical path.
VALUES_BLOSC = ("lz4", 5, "shuffle")


@dataclass(frozen=True, eq=False)
class ArraySpec:
    """One array of a store: ``name``, numpy ``dtype``, ``shape`` and ``chunks`` (in ``dims`` order),
    its attributes (CF: long_name, units...), ``fill``: the CF ``_FillValue`` (NaN for the values
    and provenance layers; None: no missing values, e.g. coordinates), ``values_codec``: compressed
    with ``values_blosc`` ((cname, clevel, shuffle), default :data:`VALUES_BLOSC`; None: stored
    uncompressed) (else zarr's default codecs of its version), ``data``: the array's
    values (coordinates, written as one chunk) or None (no chunk written: reads as the fill value)."""

    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dims: tuple[str, ...]
    attrs: dict = field(default_factory=dict)
    fill: float | None = None
    values_codec: bool = False
    data: np.ndarray | None = None
    values_blosc: tuple[str, int, str] | None = VALUES_BLOSC


def _fill_attr(fill: float) -> str:
    """xarray's encoding of a float ``_FillValue`` attribute in Zarr v3: base64 of the float64 bytes."""
    return base64.standard_b64encode(struct.pack("<d", float(fill))).decode()


@functools.lru_cache(maxsize=64)
def _zdtype(dtype: np.dtype, zarr_format: int):
    """zarr's data type object of ``dtype`` (its registry lookup costs ~0.3 ms: done once)."""
    import warnings

    from zarr.dtype import parse_dtype

    with warnings.catch_warnings():   # fixed-width text (an index output's band names): no Zarr v3 spec yet
        warnings.filterwarnings("ignore", message=".*does not have a Zarr V3 specification")
        return parse_dtype(dtype, zarr_format=zarr_format)


def _metadata(spec: ArraySpec, zarr_format: int):
    """zarr's metadata object of ``spec`` (what xarray's ``to_zarr`` makes for the variable)."""
    dtype = np.dtype(spec.dtype)
    attrs = dict(spec.attrs)
    blosc = spec.values_blosc if spec.values_codec else VALUES_BLOSC
    if zarr_format == 2:
        from zarr.core.metadata.v2 import ArrayV2Metadata

        attrs["_ARRAY_DIMENSIONS"] = list(spec.dims)
        return ArrayV2Metadata(shape=spec.shape, dtype=_zdtype(dtype, 2), chunks=spec.chunks,
                               fill_value=spec.fill, order="C", dimension_separator=".",
                               compressor=None if blosc is None else numcodecs_blosc(*blosc), filters=None,
                               attributes=attrs)
    from zarr.codecs import BloscCodec, BytesCodec, ZstdCodec
    from zarr.core.metadata.v3 import ArrayV3Metadata

    if spec.fill is not None:
        attrs["_FillValue"] = _fill_attr(spec.fill)
    compressor = (BloscCodec(typesize=dtype.itemsize, cname=blosc[0], clevel=blosc[1], shuffle=blosc[2])
                  if spec.values_codec and blosc is not None
                  else None if spec.values_codec else ZstdCodec(level=0, checksum=False))
    # xarray gives no fill value for coordinates: zarr's default, NaN for floats and 0 for integers
    fill = spec.fill if spec.fill is not None else (np.nan if dtype.kind == "f" else 0)
    return ArrayV3Metadata(shape=spec.shape, data_type=_zdtype(dtype, 3),
                           chunk_grid={"name": "regular", "configuration": {"chunk_shape": list(spec.chunks)}},
                           chunk_key_encoding={"name": "default", "configuration": {"separator": "/"}},
                           fill_value=fill, codecs=[BytesCodec(endian=None if dtype.itemsize == 1 else "little"),
                                                    *([] if compressor is None else [compressor])],
                           attributes=attrs, dimension_names=list(spec.dims) or None, storage_transformers=None)


def _encode_chunk(spec: ArraySpec, zarr_format: int) -> bytes:
    """The bytes of ``spec``'s single chunk (``data``, little-endian C order), as zarr writes them."""
    data = np.ascontiguousarray(spec.data, dtype=np.dtype(spec.dtype).newbyteorder("<"))
    if tuple(data.shape) != tuple(spec.chunks):
        raise ValueError(f"{spec.name}: data of shape {data.shape} is not one chunk {spec.chunks}")
    blosc = spec.values_blosc if spec.values_codec else VALUES_BLOSC
    if (zarr_format == 2 or spec.values_codec) and blosc is None:
        return data.tobytes()
    if zarr_format == 2 or spec.values_codec:
        return bytes(numcodecs_blosc(*blosc, typesize=data.dtype.itemsize).encode(data))
    import numcodecs

    return bytes(numcodecs.Zstd(level=0, checksum=False).encode(data.tobytes()))


def _write(path: Path, data: bytes) -> None:
    # plain writes: the store is made under a temporary name and renamed into place when complete
    with open(path, "wb") as f:
        f.write(data)


def _write_documents(root: Path, prefix: str, documents: dict) -> None:
    for key, buffer in documents.items():
        _write(root / prefix / key, buffer.to_bytes())


def _write_arrays(root: Path, arrays: list[ArraySpec], zarr_format: int) -> dict:
    """Write each array's documents and its chunk (when it has data); name -> metadata."""
    from zarr.core.buffer import default_buffer_prototype

    prototype = default_buffer_prototype()
    metas = {}
    for spec in arrays:
        meta = metas[spec.name] = _metadata(spec, zarr_format)
        (root / spec.name).mkdir(exist_ok=True)
        _write_documents(root, spec.name, meta.to_buffer_dict(prototype))
        if spec.data is not None and np.asarray(spec.data).ndim > 0:   # a 0-d 0 is zarr's fill: never written
            key = meta.encode_chunk_key((0,) * len(spec.shape))
            path = root / spec.name / key
            path.parent.mkdir(parents=True, exist_ok=True)
            _write(path, _encode_chunk(spec, zarr_format))
    return metas


def _write_root(root: Path, attrs: dict, metas: dict, zarr_format: int) -> None:
    """The group's documents with every array's metadata consolidated (the root written last)."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.group import ConsolidatedMetadata, GroupMetadata

    group = GroupMetadata(attributes=attrs, zarr_format=zarr_format,
                          consolidated_metadata=ConsolidatedMetadata(metadata=dict(metas)))
    docs = group.to_buffer_dict(default_buffer_prototype())
    if zarr_format == 2:   # .zmetadata last: a reader that sees it sees the whole store
        docs = {k: docs[k] for k in sorted(docs, key=lambda k: k == ".zmetadata")}
    _write_documents(root, "", docs)


def write_store(path: str | os.PathLike, attrs: dict, arrays: list[ArraySpec], zarr_format: int) -> None:
    """Create the Zarr store ``path`` (``zarr_format`` 2 or 3): a group with ``attrs`` holding
    ``arrays``, its metadata consolidated. FileExistsError when ``path`` holds a store already."""
    if zarr_format not in (2, 3):
        raise ValueError(f"zarr_format must be 2 or 3, got {zarr_format!r}")
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    for doc in (".zgroup", ".zarray", "zarr.json"):
        if (root / doc).exists():
            raise FileExistsError(f"{root}: a Zarr store exists there already")
    metas = _write_arrays(root, arrays, zarr_format)
    _write_root(root, attrs, metas, zarr_format)


def _read_consolidated(root: Path) -> tuple[int, dict, dict]:
    """(zarr format, root attributes, name -> array metadata) of a store :func:`write_store` made."""
    if (root / "zarr.json").exists():
        from zarr.core.group import GroupMetadata

        group = GroupMetadata.from_dict(json.loads((root / "zarr.json").read_text()))
        return 3, dict(group.attributes), dict(group.consolidated_metadata.metadata)
    from zarr.core.metadata.v2 import ArrayV2Metadata

    docs = json.loads((root / ".zmetadata").read_text())["metadata"]
    metas = {}
    for key, doc in docs.items():
        if key.endswith("/.zarray"):
            name = key[:-len("/.zarray")]
            metas[name] = ArrayV2Metadata.from_dict({**doc, "attributes": docs.get(f"{name}/.zattrs", {})})
    return 2, dict(docs[".zattrs"]), metas


def add_arrays(path: str | os.PathLike, arrays: list[ArraySpec], attrs: dict | None = None) -> int:
    """Add ``arrays`` to the store ``path`` (made by :func:`write_store`, same Zarr version), update
    its root attributes with ``attrs`` and consolidate its metadata again; returns the version."""
    root = Path(path)
    zarr_format, root_attrs, metas = _read_consolidated(root)
    metas.update(_write_arrays(root, arrays, zarr_format))
    root_attrs.update(attrs or {})
    _write_root(root, root_attrs, metas, zarr_format)
    return zarr_format
