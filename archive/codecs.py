"""Compression of the outputs' chunks and tiles, in one place.

- :class:`Compression`: what ``archive render --compression NAME`` (``compression=`` of the Python
  API) picks, for each format at once: the Zarr values' Blosc (or none) and the COG tiles' Zstandard
  level and TIFF predictor (or none). ENVI is never compressed. :data:`COMPRESSIONS` holds the
  choices, :data:`DEFAULT_COMPRESSION` the default; the table they were chosen by (CPU-seconds per
  cube against bytes on disk, rendered radiance) is in README "Compression" and bench/RESULTS.md
  (issue 37).
- :func:`numcodecs_blosc`: the numcodecs Blosc that produces, from a chunk's little-endian C-order
  bytes, the very bytes zarr writes for a Blosc codec. The collection store
  (:mod:`archive.collection`, ingest) and the Zarr output (:mod:`archive.outputs.zarr`, the render's
  tile tasks) both write whole chunks without zarr's per-chunk pipeline (about as costly again as
  the compression); both build their codec here.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["COMPRESSIONS", "DEFAULT_COMPRESSION", "SHUFFLES", "Compression", "compression", "numcodecs_blosc"]

#: zarr's Blosc shuffle names -> numcodecs' shuffle constants.
SHUFFLES = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}


@dataclass(frozen=True)
class Compression:
    """One ``--compression`` choice. ``zarr_blosc``: (cname, clevel, shuffle by zarr's name) of the
    Zarr values' Blosc codec, None: chunks stored uncompressed; ``cog_zstd``: the COG tiles'
    Zstandard level (negative: zstd's fast levels), None: tiles stored uncompressed; ``cog_predictor``:
    TIFF predictor of the COG tiles, 3 (floating point, before Zstandard) or 1 (none)."""

    name: str
    zarr_blosc: tuple[str, int, str] | None
    cog_zstd: int | None
    cog_predictor: int

    @property
    def cog_tag(self) -> int:
        """The TIFF ``Compression`` tag: 50000 (Zstandard) or 1 (none)."""
        return 1 if self.cog_zstd is None else 50000


#: The choices, by name (bench/RESULTS.md issue 37: CPU-s per paper cube of 300 bands, one thread):
#: ``fast`` (default): Blosc LZ4 5 + byte shuffle (~0.5 encode, ratio ~1.45) and COG ZSTD -3 +
#: floating-point predictor (~1.35, ratio ~1.6), the cheapest per byte saved; ``small``: Blosc Zstd 1
#: + shuffle (~5x the CPU, 8 % fewer bytes) and COG ZSTD 1 + predictor (+40 % CPU, 7 % fewer bytes);
#: ``none``: uncompressed (Zarr pads edge chunks and writes twice the bytes: more CPU in the kernel
#: than LZ4 costs; COG tiles as raw float32).
COMPRESSIONS = {
    "fast": Compression("fast", ("lz4", 5, "shuffle"), -3, 3),
    "small": Compression("small", ("zstd", 1, "shuffle"), 1, 3),
    "none": Compression("none", None, None, 1),
}
DEFAULT_COMPRESSION = "fast"


def compression(name: str | Compression | None) -> Compression:
    """The :class:`Compression` called ``name`` (None: the default); InputError naming
    ``--compression`` for an unknown name."""
    if isinstance(name, Compression):
        return name
    key = DEFAULT_COMPRESSION if name is None else str(name).strip().lower()
    if key not in COMPRESSIONS:
        from archive.errors import InputError

        raise InputError("--compression", f"unknown compression {name!r}",
                         f"use one of {', '.join(COMPRESSIONS)} (README 'Compression')")
    return COMPRESSIONS[key]


def numcodecs_blosc(cname: str, clevel: int, shuffle: str, blocksize: int = 0, typesize: int | None = None):
    """numcodecs.Blosc(cname, clevel, shuffle, blocksize[, typesize]); ``shuffle`` by zarr's name
    ('noshuffle' | 'shuffle' | 'bitshuffle'); ``typesize`` None: the item size of what is encoded."""
    import numcodecs

    extra = {} if typesize is None else {"typesize": int(typesize)}
    return numcodecs.Blosc(cname=cname, clevel=int(clevel), shuffle=SHUFFLES[shuffle], blocksize=int(blocksize),
                           **extra)
