"""``archive render --compression`` (issue 37): the same values whatever the choice, the codecs the
files say, the bytes each choice costs, and a clear error for an unknown name.

One small simulated flight rendered to Zarr (v2 and v3) and COG with each choice on one shared
local cluster; values compared bit for bit with the default's, the Zarr metadata and the COG's TIFF
tags read back by zarr and GDAL (rasterio), GDAL's COG checks on every COG.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import xarray as xr

from archive.cli import main
from archive.codecs import COMPRESSIONS, DEFAULT_COMPRESSION, compression
from archive.errors import InputError
from archive.run.options import RenderOptions
from archive.outputs.cog_check import check_cog
from archive.outputs.tiff import decode_tile, encode_tile, float_predictor
from helpers import FOV

GSD = 0.02   # ~1760 x 400 px: two chunk columns, 4 x 1 COG tiles and 2 overview levels


@pytest.fixture(scope="module")
def rendered(small_flight, scheduler, tmp_path_factory):
    """{(name, suffix): path} of the small flight rendered with every compression to .zarr (v2),
    .tif, and with 'none' to a Zarr v3 store."""
    folder = tmp_path_factory.mktemp("compression")
    out = {}
    runs = [(name, suffix, []) for name in COMPRESSIONS for suffix in (".zarr", ".tif")]
    runs.append(("none", ".v3.zarr", ["--zarr-format", "3"]))
    for name, suffix, extra in runs:
        path = folder / f"{name}{suffix}"
        assert main(["render", str(small_flight), "--fov", str(FOV), "--gsd", str(GSD), "--ground-height", "auto",
                     "--out", str(path), "--quiet", "--scheduler", scheduler, "--compression", name, *extra]) == 0
        out[name, suffix] = path
    return out


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def _zarr_values(path) -> np.ndarray:
    return xr.open_zarr(path, decode_coords="all")["radiance"].values


def _chunk_bytes(path) -> int:
    return sum(f.stat().st_size for f in (path / "radiance").rglob("*") if f.is_file() and not f.name.startswith("."))


def test_every_choice_holds_the_same_values(rendered):
    reference = _zarr_values(rendered[DEFAULT_COMPRESSION, ".zarr"])
    assert np.isfinite(reference).any() and np.isnan(reference).any()
    for (name, suffix), path in rendered.items():
        if suffix.endswith(".zarr"):
            values = _zarr_values(path)
        else:
            assert check_cog(path) == [], name
            with rasterio.open(path) as ds:
                values = ds.read()
        np.testing.assert_array_equal(_bits(values), _bits(reference), err_msg=f"{name}{suffix}")


def test_zarr_metadata_names_the_codec_and_bytes_follow_it(rendered):
    sizes = {}
    for name, choice in COMPRESSIONS.items():
        path = rendered[name, ".zarr"]
        meta = json.loads((path / "radiance" / ".zarray").read_text())
        if choice.zarr_blosc is None:
            assert meta["compressor"] is None
        else:
            cname, clevel, shuffle = choice.zarr_blosc
            assert meta["compressor"]["id"] == "blosc"
            assert (meta["compressor"]["cname"], meta["compressor"]["clevel"]) == (cname, clevel)
        sizes[name] = _chunk_bytes(path)
    # uncompressed chunks are whole float32 chunks: 1024 x 1024 x 4 bytes each
    nchunks = sum(1 for f in (rendered["none", ".zarr"] / "radiance").iterdir() if not f.name.startswith("."))
    assert sizes["none"] == nchunks * 1024 * 1024 * 4
    assert sizes["small"] < sizes["fast"] < 0.8 * sizes["none"]
    # Zarr v3 without compressor: the bytes codec alone
    v3 = json.loads((rendered["none", ".v3.zarr"] / "radiance" / "zarr.json").read_text())
    assert [c["name"] for c in v3["codecs"]] == ["bytes"]


def test_cog_tags_name_the_codec_and_bytes_follow_it(rendered):
    sizes = {}
    for name, choice in COMPRESSIONS.items():
        path = rendered[name, ".tif"]
        with rasterio.open(path) as ds:
            structure = ds.tags(ns="IMAGE_STRUCTURE")
            assert structure["LAYOUT"] == "COG"
            if choice.cog_zstd is None:
                assert "COMPRESSION" not in structure and ds.compression is None
            else:
                assert structure["COMPRESSION"] == "ZSTD" and structure["PREDICTOR"] == str(choice.cog_predictor)
        sizes[name] = path.stat().st_size
    assert sizes["small"] < sizes["fast"] < 0.8 * sizes["none"]


@pytest.mark.parametrize("name", list(COMPRESSIONS))
def test_tile_codec_round_trip(name):
    """Every choice's COG tile encoding decodes to the same bits (NaN, edges and values)."""
    c = compression(name)
    rng = np.random.default_rng(1)
    tile = rng.normal(40.0, 5.0, (512, 512)).astype(np.float32)
    tile[:, 400:] = np.nan
    data = encode_tile(tile, c.cog_zstd, c.cog_predictor)
    back = decode_tile(data, compressed=c.cog_zstd is not None, predictor=c.cog_predictor)
    np.testing.assert_array_equal(_bits(back), _bits(tile))
    assert (len(data) == tile.nbytes) == (c.cog_zstd is None)


def _fp_diff(tile: np.ndarray) -> np.ndarray:
    """libtiff's fpDiff written out byte by byte (TIFF technical note 3): per row, the bytes of each
    pixel big-endian, byte k of every pixel before byte k + 1, then each byte minus the previous
    one modulo 256."""
    import struct

    h, w = tile.shape
    out = np.empty((h, 4 * w), np.uint8)
    for y in range(h):
        be = [struct.pack(">f", float(v)) if np.isfinite(v) else int(np.float32(v).view(np.uint32)).to_bytes(4, "big")
              for v in tile[y]]
        row = [be[x][k] for k in range(4) for x in range(w)]
        out[y] = [row[0]] + [(row[i] - row[i - 1]) % 256 for i in range(1, 4 * w)]
    return out


def test_float_predictor_is_libtiffs_fpdiff_on_views_and_special_values():
    """The predictor (planes by shifts, no transpose copy) gives fpDiff's bytes, from a tile that
    is a view of a wider chunk too (as the writer hands its 2 x 2 tiles), and so the same file bytes."""
    rng = np.random.default_rng(5)
    chunk = rng.normal(40.0, 30.0, (12, 22)).astype(np.float32)
    chunk.flat[::7] = np.nan
    chunk[0, :8] = [np.inf, -np.inf, -0.0, 0.0, 1e-45, -3e38, np.float32(np.uint32(0xFFC00000).view(np.float32)), 1.0]
    for tile in (chunk, chunk[2:9, 11:20], np.ascontiguousarray(chunk[2:9, 11:20])):
        np.testing.assert_array_equal(float_predictor(tile), _fp_diff(tile))
    view = chunk[:, 11:]
    assert encode_tile(view) == encode_tile(np.ascontiguousarray(view))
    back = decode_tile(encode_tile(view), shape=view.shape)
    np.testing.assert_array_equal(_bits(back), _bits(view))


def test_unknown_compression_is_a_one_line_error(small_flight, capsys):
    with pytest.raises(InputError, match="--compression: unknown compression 'lzma'.*fast, small, none"):
        RenderOptions.create([str(small_flight)], gsd=GSD, fov=FOV, compression="lzma")
    assert RenderOptions.create([str(small_flight)], gsd=GSD, fov=FOV).compression == DEFAULT_COMPRESSION
    with pytest.raises(SystemExit) as exc:
        main(["render", str(small_flight), "--gsd", "1", "--out", "x.zarr", "--compression", "lzma"])
    assert exc.value.code == 2 and "--compression: invalid choice: 'lzma'" in capsys.readouterr().err


def test_a_stack_refuses_another_compression(small_archive, tmp_path, capsys):
    arc, cid = small_archive
    code = main(["render", cid, "--archive", str(arc), "--stack", "--gsd", "0.1", "--out", str(tmp_path / "s.zarr"),
                 "--compression", "small", "--quiet"])
    assert code == 2 and "--compression: a stack is written with the default compression" in capsys.readouterr().err
    assert not (tmp_path / "s.zarr").exists()


def test_a_stack_refuses_another_compression_in_python(small_archive, tmp_path):
    import archive

    arc, cid = small_archive
    with pytest.raises(InputError, match=r"georectify\(compression=...\): a stack is written with the default compression"):
        archive.georectify([cid], tmp_path / "s.zarr", archive=str(arc), stack=True, gsd=0.1, compression="small")
    assert not (tmp_path / "s.zarr").exists()
