"""Zarr chunks encoded directly: the numcodecs Blosc that produces, from a chunk's little-endian
C-order bytes, the very bytes zarr writes for a Blosc codec.

The collection store (:mod:`archive.collection`, ingest) and the Zarr output
(:mod:`archive.outputs.zarr`, the render's tile tasks) both write whole chunks without zarr's
per-chunk pipeline (about as costly again as the compression); both build their codec here.
"""

from __future__ import annotations

__all__ = ["SHUFFLES", "numcodecs_blosc"]

#: zarr's Blosc shuffle names -> numcodecs' shuffle constants.
SHUFFLES = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}


def numcodecs_blosc(cname: str, clevel: int, shuffle: str, blocksize: int = 0, typesize: int | None = None):
    """numcodecs.Blosc(cname, clevel, shuffle, blocksize[, typesize]); ``shuffle`` by zarr's name
    ('noshuffle' | 'shuffle' | 'bitshuffle'); ``typesize`` None: the item size of what is encoded."""
    import numcodecs

    extra = {} if typesize is None else {"typesize": int(typesize)}
    return numcodecs.Blosc(cname=cname, clevel=int(clevel), shuffle=SHUFFLES[shuffle], blocksize=int(blocksize),
                           **extra)
