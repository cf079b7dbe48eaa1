"""The collection format, owned by this package alone: one raw flight ingested into a chunked,
compressed Zarr v3 group — attribute names, codecs, completion marker, chunk paths, digests
(:mod:`.layout`), written by ingest (:mod:`.write`), given new navigation by ``calibrate --apply``
(:mod:`.update`), verified (:mod:`.verify`) and read back (:mod:`.read`: the collection source,
the catalog). No other module knows this layout.

Layout of ``<ARCHIVE>/collections/<id>.zarr`` (axis orders in brackets)::

    dn            [band, line, sample]  raw DN, all cubes' lines in capture order, native dtype
                  (uint16 for Resonon), one chunk = one band x CHUNK_LINES lines (see below)
    dn_blake3     [band, chunk, 32]     digest of each decoded dn chunk (C order, little endian) by the algorithm
                  the attribute ``archive:dn_checksum`` names: ``dn_blake3`` (BLAKE3, the default) or
                  ``dn_sha256`` (``--checksum sha256``, and every store of format 1, which has no attribute)
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
every cube's full header metadata, the source files (name, size, and their digest under the
algorithm's name: ``blake3``, or ``sha256``), calibration reference
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

from archive.collection.layout import (CHECKSUMS, COMPLETE, DEFAULT_CHECKSUM, DN_CODEC, DN_COMPRESSIONS, FORMAT,
                                       FORMAT_VERSION, NAV_COLUMNS, SMALL_CODEC, array_digest, chunk_digest,
                                       chunk_lines_for, chunk_path, digest_table, dn_checksum, file_digest, is_complete,
                                       sha256_file)
from archive.collection.read import (CheckedDn, CollectionInfo, CorruptChunkError, StoredCalibration, StoredCube,
                                     StoredPoses, content_version, frame_from_attrs, frame_to_attrs, open_dn,
                                     read_attrs, read_downwelling, read_info, read_poses, read_track)
from archive.collection.update import check_updatable, record_navigation, settle
from archive.collection.verify import verify_store
from archive.collection.write import (TEST_HOLD_AFTER_CHUNKS, ChunkGroup, ChunkTask, StorePlan, chunk_groups,
                                      chunk_tasks, finish_store, hash_file_task, open_partial, publish, store_lock,
                                      write_chunk, write_chunks)

__all__ = ["CHECKSUMS", "COMPLETE", "DEFAULT_CHECKSUM", "DN_CODEC", "DN_COMPRESSIONS", "FORMAT", "FORMAT_VERSION",
           "NAV_COLUMNS", "SMALL_CODEC", "TEST_HOLD_AFTER_CHUNKS", "CheckedDn", "ChunkGroup", "ChunkTask", "CollectionInfo", "CorruptChunkError", "StorePlan",
           "StoredCalibration", "StoredCube", "StoredPoses", "array_digest", "chunk_digest", "chunk_lines_for",
           "chunk_groups", "chunk_path", "chunk_tasks", "digest_table", "dn_checksum", "file_digest", "check_updatable", "content_version", "finish_store", "frame_from_attrs",
           "frame_to_attrs", "hash_file_task", "is_complete", "open_dn", "open_partial", "publish", "read_attrs",
           "read_downwelling", "read_info", "read_poses", "read_track", "record_navigation", "settle",
           "sha256_file", "store_lock", "verify_store", "write_chunk", "write_chunks"]
