"""Flight directory discovery: capture order, completeness checks, calibration lookup."""

from __future__ import annotations

from pathlib import Path

import pytest

from archive.errors import FormatError, InputError, MissingInputError
from archive.formats.flight import discover_flight, natural_key


def _cube(directory: Path, base: str, first_time: float, suffix: str = ".bil",
          skip: tuple[str, ...] = (), step: float = 0.01) -> None:
    files = {"data": directory / f"{base}{suffix}", "header": directory / f"{base}{suffix}.hdr",
             "lcf": directory / f"{base}.lcf", "times": directory / f"{base}{suffix}.times"}
    contents = {"data": "", "header": "ENVI\n", "lcf": "",
                "times": f"{first_time:.6f}\n{first_time + step:.6f}\n"}
    for kind, path in files.items():
        if kind not in skip:
            path.write_text(contents[kind])


def test_capture_order_and_tie_break(tmp_path):
    _cube(tmp_path, "flight_Pika_L_10", 50.0)
    _cube(tmp_path, "flight_Pika_L_2", 20.0)
    _cube(tmp_path, "flight_Pika_L_9", 10.0, suffix=".bip")
    _cube(tmp_path, "flight_Pika_L_3", 20.0, step=0.02)  # same first time as _2: natural sort decides
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "white.hdr").write_text("ENVI\n")  # unrelated header: ignored
    flight = discover_flight(tmp_path)
    assert [c.base for c in flight.cubes] == ["flight_Pika_L_9", "flight_Pika_L_2",
                                              "flight_Pika_L_3", "flight_Pika_L_10"]
    first = flight.cubes[0]
    assert first.data == tmp_path / "flight_Pika_L_9.bip"
    assert first.header == tmp_path / "flight_Pika_L_9.bip.hdr"
    assert first.lcf == tmp_path / "flight_Pika_L_9.lcf"
    assert first.times == tmp_path / "flight_Pika_L_9.bip.times"
    assert flight.directory == tmp_path and flight.calibration is None


def test_natural_key():
    names = ["a_10", "a_9", "a_100", "b_1", "a_1"]
    assert sorted(names, key=natural_key) == ["a_1", "a_9", "a_10", "a_100", "b_1"]


def test_calibration_lookup(tmp_path):
    _cube(tmp_path, "c_1", 1.0)
    (tmp_path / "imager.icp").write_bytes(b"")
    assert discover_flight(tmp_path).calibration == tmp_path / "imager.icp"
    (tmp_path / "other.icp").write_bytes(b"")
    with pytest.raises(InputError, match=r"2 calibration files.*--calibration"):
        discover_flight(tmp_path)


@pytest.mark.parametrize("skip, missing", [(("lcf",), r"c_2\.lcf"),
                                           (("times",), r"c_2\.bil\.times"),
                                           (("header",), r"c_2\.bil\.hdr")])
def test_cube_missing_a_file(tmp_path, skip, missing):
    _cube(tmp_path, "c_1", 1.0)
    _cube(tmp_path, "c_2", 2.0, skip=skip)
    with pytest.raises(MissingInputError, match=rf"{missing}.* of cube c_2 not found"):
        discover_flight(tmp_path)


def test_header_without_data(tmp_path):
    _cube(tmp_path, "c_1", 1.0)
    _cube(tmp_path, "c_2", 2.0, skip=("data",))
    with pytest.raises(FormatError, match=r"c_2\.bil\.hdr: header without its data file c_2\.bil"):
        discover_flight(tmp_path)


def test_two_data_files_for_one_base(tmp_path):
    _cube(tmp_path, "c_1", 1.0)
    _cube(tmp_path, "c_1", 1.0, suffix=".bsq")
    with pytest.raises(FormatError, match=r"cube c_1 has two data files"):
        discover_flight(tmp_path)


def test_missing_or_empty_directory(tmp_path):
    with pytest.raises(MissingInputError, match=r"nowhere: flight directory not found"):
        discover_flight(tmp_path / "nowhere")
    with pytest.raises(InputError, match=r"no cubes found"):
        discover_flight(tmp_path)
    (tmp_path / "f").write_text("")
    with pytest.raises(InputError, match=r"not a directory"):
        discover_flight(tmp_path / "f")


def test_bad_times_named(tmp_path):
    _cube(tmp_path, "c_1", 1.0)
    (tmp_path / "c_1.bil.times").write_text("abc\n")
    with pytest.raises(FormatError, match=r"c_1\.bil\.times: line 1"):
        discover_flight(tmp_path)


def test_duplicated_cube_is_refused(tmp_path):
    _cube(tmp_path, "flight_Pika_L_1", 20.0)
    _cube(tmp_path, "flight_Pika_L_1_copy", 20.0)  # the same capture under another name
    with pytest.raises(InputError, match="flight_Pika_L_1 and flight_Pika_L_1_copy hold the same capture"):
        discover_flight(tmp_path)
