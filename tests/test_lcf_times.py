"""LCF navigation, GPS time conversion and .times files: real samples, round trips, bad inputs."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from archive.errors import FormatError, MissingInputError
from archive.formats.lcf import (LcfData, fix_gps_week, gps_seconds_to_datetime, read_lcf,
                                write_lcf)
from archive.formats.times import first_time, read_times, write_times

AVSTJOHN = "avstjohn__hyperspectral_analysis/20160228_17h18m_pika_L_1"
MASSIMAL = "mh-skjelvareid__massimal/Juvika_June2022_Pika_L_"
BURUNDUKE = "Burunduke__gaps_filler/manual_Pika_L_28"


def test_avstjohn_lcf(resonon_samples):
    lcf = read_lcf(resonon_samples / f"{AVSTJOHN}.lcf")
    assert len(lcf) == 3525 and lcf.time.shape == (3525,)
    assert lcf.time[0] == 521399904.25
    assert lcf.roll[0] == 0.0167342610657 and lcf.pitch[0] == -0.0368618406355
    assert lcf.yaw[0] == 2.58900642395
    assert lcf.lon[0] == -90.0166427826 and lcf.lat[0] == 38.86580109  # lon before lat
    assert lcf.alt[0] == 424.124335958
    assert np.allclose(np.diff(lcf.time), 0.005, atol=1e-6)
    # week-mod-1024 file: maps to the header timestamp 02/28/2016-17h18m (GPS, ~17 s ahead of UTC)
    utc = gps_seconds_to_datetime(lcf.time[0])
    assert abs(utc - datetime(2016, 2, 28, 17, 18, 30, tzinfo=UTC)) < timedelta(minutes=1)


def test_massimal_lcf(resonon_samples):
    lcf12 = read_lcf(resonon_samples / f"{MASSIMAL}12.lcf")
    lcf13 = read_lcf(resonon_samples / f"{MASSIMAL}13.lcf")
    assert len(lcf12) == 3668 and len(lcf13) == 3668
    assert lcf12.time[0] == 1340119934.235
    assert lcf12.lon[0] == 15.005044096171448 and lcf12.lat[0] == 67.21564224691991
    assert lcf12.alt[0] == 38.51876425148946
    assert lcf13.time[0] > lcf12.time[-1]
    utc = gps_seconds_to_datetime(1340119934.235)
    assert utc == datetime(2022, 6, 24, 15, 31, 56, 235000, tzinfo=UTC)


def test_burunduke_excerpt_with_trailing_tabs(resonon_samples):
    path = resonon_samples / f"{BURUNDUKE}.lcf.excerpt"
    assert path.read_text().splitlines()[0].endswith("\t")
    lcf = read_lcf(path)
    assert len(lcf) == 20
    assert lcf.time[0] == 1371805399.915 and lcf.yaw[0] == -1.5826479196548462
    assert lcf.alt[0] == 91.78055037958092
    assert gps_seconds_to_datetime(lcf.time[0]) == datetime(2023, 6, 26, 9, 3, 1, 915000,
                                                            tzinfo=UTC)


def test_times_samples(resonon_samples):
    t = read_times(resonon_samples / f"{AVSTJOHN}.bil.times", expected_lines=2114)
    assert t.shape == (2114,) and t[0] == 1563.736884
    assert 1 / np.median(np.diff(t)) == pytest.approx(120.0048, abs=0.01)
    assert not (resonon_samples / f"{AVSTJOHN}.bil.times").read_bytes().endswith(b"\n")
    t12 = read_times(resonon_samples / f"{MASSIMAL}12.bil.times", expected_lines=2000)
    t13 = read_times(resonon_samples / f"{MASSIMAL}13.bil.times", expected_lines=2000)
    assert (t12[0], t12[-1], t13[0]) == (876.386137, 894.725574, 894.742683)
    ex = read_times(resonon_samples / f"{BURUNDUKE}.bil.times.excerpt")
    assert ex.shape == (20,) and ex[0] == 263.873396
    assert first_time(resonon_samples / f"{MASSIMAL}13.bil.times") == 894.742683


def test_leap_seconds_and_week_fix():
    t = (datetime(2017, 1, 1, tzinfo=UTC) - datetime(1980, 1, 6, tzinfo=UTC)).total_seconds()
    assert gps_seconds_to_datetime(t + 18) == datetime(2017, 1, 1, tzinfo=UTC)
    assert gps_seconds_to_datetime(t + 16) == datetime(2016, 12, 31, 23, 59, 59, tzinfo=UTC)
    t2010 = (datetime(2010, 5, 1, tzinfo=UTC) - datetime(1980, 1, 6, tzinfo=UTC)).total_seconds()
    assert gps_seconds_to_datetime(t2010 + 15) == datetime(2010, 5, 1, tzinfo=UTC)
    assert gps_seconds_to_datetime(t2010 + 15 - 1024 * 604800) == datetime(2010, 5, 1, tzinfo=UTC)
    assert gps_seconds_to_datetime(100.0).year == 1999  # one rollover by default
    # a mod-1024 time from after the 2019 rollover needs two rollovers: choose by a reference date
    t2021 = (datetime(2021, 3, 1, tzinfo=UTC) - datetime(1980, 1, 6, tzinfo=UTC)).total_seconds()
    wrapped = t2021 - 2048 * 604800
    assert fix_gps_week(wrapped, near=datetime(2021, 3, 1)) == t2021
    assert gps_seconds_to_datetime(wrapped, near=datetime(2021, 3, 1)).date().isoformat() == \
        "2021-02-28"  # 23:59:42 UTC after the 18 s leap correction


def test_lcf_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    n = 50
    data = LcfData(None, 1.3e9 + np.arange(n) * 0.005 + rng.normal(0, 1e-7, n),
                   *(rng.normal(0, 1, (6, n))))
    write_lcf(tmp_path / "x.lcf", data)
    rows = (tmp_path / "x.lcf").read_text().splitlines()
    assert len(rows) == n
    fields = rows[0].split("\t")
    assert len(fields) == 11 and fields[7:] == ["0", "0", "5", "4"]
    back = read_lcf(tmp_path / "x.lcf")
    assert back.path == tmp_path / "x.lcf"
    for name in ("time", "roll", "pitch", "yaw", "lon", "lat", "alt"):
        np.testing.assert_array_equal(getattr(back, name), getattr(data, name))


def test_times_round_trip(tmp_path):
    t = 876.386137 + np.cumsum(np.full(300, 1 / 109.0037)) + 1e-7 * np.sin(np.arange(300))
    write_times(tmp_path / "x.bil.times", t)
    text = (tmp_path / "x.bil.times").read_text()
    assert text.endswith("\n") and len(text.splitlines()) == 300
    back = read_times(tmp_path / "x.bil.times", expected_lines=300)
    assert np.max(np.abs(back - t)) < 1e-6


GOOD = "1.0\t0\t0\t0\t10\t50\t100\t0\t0\t5\t4\n"


@pytest.mark.parametrize("text, message", [
    ("", "no navigation rows"),
    ("# only a comment\n\n", "no navigation rows"),
    (GOOD + "2.0\t0\t0\t0\t10\t50\t100\t0\t0\n", r"line 2: 9 columns"),
    (GOOD + "2.0\t0\tnan\t0\t10\t50\t100\t0\t0\t5\n", r"line 2, column 3.*not finite"),
    (GOOD + "2.0\t0\t0\t0\t10\tinf\t100\t0\t0\t5\n", r"line 2, column 6.*not finite"),
    (GOOD + "2.0\t0\t0\tx\t10\t50\t100\t0\t0\t5\n", r"line 2, column 4: 'x' is not a number"),
    ("\n" + GOOD + GOOD, r"line 3: time 1.0 does not increase"),
])
def test_bad_lcf(tmp_path, text, message):
    path = tmp_path / "bad.lcf"
    path.write_text(text)
    with pytest.raises(FormatError, match=rf"bad\.lcf: {message}"):
        read_lcf(path)


def test_lcf_comments_extra_columns(tmp_path):
    path = tmp_path / "ok.lcf"
    path.write_text("# header\n" + GOOD + "\n" + "2.0 0 0 0 11 51 101 0 0 5 4 99 98\t\n")
    lcf = read_lcf(path)
    np.testing.assert_array_equal(lcf.time, [1.0, 2.0])
    np.testing.assert_array_equal(lcf.lon, [10.0, 11.0])


@pytest.mark.parametrize("text, expected, message", [
    ("", None, "no line times"),
    ("\n\n", None, "no line times"),
    ("1.0\n2.0\nabc\n", None, r"line 3: 'abc' is not a number"),
    ("1.0\nnan\n", None, r"line 2: value 'nan' is not finite"),
    ("1.0\n2.0\n2.0\n", None, r"line 3: time 2.0 does not increase"),
    ("1.0\n\n2.0\n", None, r"line 2: empty line"),
    ("1.0\n2.0\n", 3, r"2 times for 3 lines"),
    ("1.0\n2.0\n3.0\n4.0", 3, r"4 times for 3 lines"),
])
def test_bad_times(tmp_path, text, expected, message):
    path = tmp_path / "bad.bil.times"
    path.write_text(text)
    with pytest.raises(FormatError, match=rf"bad\.bil\.times: {message}"):
        read_times(path, expected_lines=expected)


def test_missing_files(tmp_path):
    with pytest.raises(MissingInputError, match=r"no\.lcf"):
        read_lcf(tmp_path / "no.lcf")
    with pytest.raises(MissingInputError, match=r"no\.bil\.times"):
        read_times(tmp_path / "no.bil.times")
    with pytest.raises(FileNotFoundError):
        first_time(tmp_path / "no.bil.times")
