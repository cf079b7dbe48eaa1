"""``archive info`` names a raw flight as ``archive ingest`` will (issue 49 item 6): one name per flight,
``<sensor>_<UTC start>``, not the directory name and GPS time it used to print."""

from __future__ import annotations

import json
import shutil

from archive.cli import main
from archive.ingest.summary import ingest_id
from archive.params import NavigationParams
from archive.sources import RawFlightSource
from helpers import FOV, TINY_FLIGHT, ingest_each


def _info_json(capsys, *argv: str) -> dict:
    capsys.readouterr()
    assert main(["info", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_info_names_a_raw_flight_as_ingest_does(tiny_flights, tmp_path, capsys):
    flight = tiny_flights(0)
    summary = _info_json(capsys, str(flight))
    (cid,) = ingest_each([flight], tmp_path / "archive")
    assert summary["id"] == cid == "Pika-L-SIM_20240612T160000"
    # the collection's own summary carries the same name
    assert _info_json(capsys, cid, "--archive", str(tmp_path / "archive"))["id"] == cid
    text = (capsys.readouterr(), main(["info", str(flight)]), capsys.readouterr().out)[2]
    assert f"(id {cid})" in text and "flight-" not in text


def test_info_name_follows_the_sync_offset_as_ingest(simulated, tmp_path, capsys):
    """A recorder whose .lcf starts 0.6 s before the first line's true time (16:01:00.5): without the
    sync offset the first line is at 16:00:59.9, with it at 16:01:00.5, for info and ingest alike."""
    flight, _ = simulated(seed=1, sync_offset=0.6, **TINY_FLIGHT)
    assert _info_json(capsys, str(flight))["id"] == "Pika-L-SIM_20240612T160059"
    summary = _info_json(capsys, str(flight), "--sync-offset", "0.6")
    (cid,) = ingest_each([flight], tmp_path / "archive", FOV, sync_offset=0.6)
    assert summary["id"] == cid == "Pika-L-SIM_20240612T160100"


def test_a_header_without_a_sensor_is_named_flight(tiny_flights, tmp_path):
    """No ``imager serial number`` (nor sensor type): ``flight_<start>``, as ingest's collection_id."""
    flight = tmp_path / "nosensor"
    shutil.copytree(tiny_flights(2), flight)
    for hdr in flight.glob("*.hdr"):
        lines = [ln for ln in hdr.read_text().splitlines()
                 if not ln.lower().startswith(("imager serial number", "sensor type", "sensor ="))]
        hdr.write_text("\n".join(lines) + "\n")
    name = ingest_id(RawFlightSource(flight, NavigationParams(sync_offset=0.0)))
    assert name == "flight_20240612T160200"
