"""``archive watch`` (issue 47): a simulated flight replayed into a folder at the camera's pace by a
helper that writes as a recorder does (tests/recorder.py: the ``.bil`` growing block by block, the
``.times`` and ``.lcf`` with it, the header last).

- completeness: a cube is never complete before its header, never while a file disagrees with it
  or moves; a cube that stays incomplete is skipped once;
- the live flight: every cube listed with imagery (the close -> imagery latency of each printed),
  the imagery where the simulator's true footprint is, one pass outline per true strip (on it within
  half a pixel), a pass not flown reported as the gap the true footprints leave; after
  ``--idle`` the collection equals a plain ``archive ingest`` of the folder (every array, every
  attribute, the catalog Item); a restarted watch ingests nothing again;
- faults: a recorder that dies mid-cube and restarts under a new image set, a folder that
  disappears, SIGTERM during an ingest (exit 0, the archive consistent), then a restart that
  finishes the job.
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from helpers import FOV
from recorder import replay

ROOT = Path(__file__).resolve().parents[1]
FLIGHT = dict(cubes=4, bands=4, samples=64, lines=150, cubes_per_pass=2, seed=5)


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> tuple[Path, object]:
    """(folder, truth) of a finished simulated flight: 4 cubes of 150 lines on 2 passes."""
    from archive.simulator.command import simulate_flight

    folder = tmp_path_factory.mktemp("watch-source") / "flight"
    return folder, simulate_flight(folder, **FLIGHT)


class Watcher:
    """``archive watch`` in a subprocess; its stdout lines collected with their arrival times."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "archive", "watch", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.lines: list[str] = []
        self.queue: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))
            self.queue.put(line)

    def wait_for(self, pattern: str, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if re.search(pattern, line):
                    return line
            assert self.proc.poll() is None, f"watch ended ({self.proc.returncode}): {self.text()}"
            time.sleep(0.02)
        pytest.fail(f"no line matching {pattern!r} in {timeout} s: {self.text()}")

    def url(self) -> str:
        return re.search(r"http://127\.0\.0\.1:\d+/", self.wait_for("live map at")).group(0)

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(30)
        time.sleep(0.1)
        return code

    def text(self) -> str:
        err = self.proc.stderr.read() if self.proc.poll() is not None else ""
        return "\n".join(self.lines) + ("\nstderr: " + err if err else "")

    def count(self, pattern: str) -> int:
        return sum(1 for line in self.lines if re.search(pattern, line))


def get(url: str):
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.status, r.read(), dict(r.headers)


# ---- completeness -------------------------------------------------------------------------------
def test_a_cube_is_complete_only_whole_and_still(source, tmp_path):
    from archive.watch.cubes import check_cube, image_set
    from archive.watch.follow import Changed, Complete, Follower, Skipped

    folder = tmp_path / "rec"
    replay(source[0], folder, cubes=slice(0, 1), stop_after=(0, 0.5), speed=50)   # dies half way: no header
    data = folder / "sim_Pika_L_1.bil"
    check = check_cube(data)
    assert not check.whole and "no header sim_Pika_L_1.bil.hdr" in check.why
    follower = Follower([folder], settle=0.0, stall=5.0)
    assert follower.scan(100.0) == [] and follower.growing()
    # a header that says more lines than the .bil holds: not whole, the file named
    (folder / "sim_Pika_L_1.bil.hdr").write_text((source[0] / "sim_Pika_L_1.bil.hdr").read_text())
    check = check_cube(data)
    assert not check.whole and "sim_Pika_L_1.bil holds" in check.why and "150 lines" in check.why
    assert follower.scan(101.0) == []                       # it moved: its stall clock starts again
    events = follower.scan(106.5)
    assert [type(e) for e in events] == [Skipped] and "sim_Pika_L_1" in events[0].cube.base
    assert follower.scan(120.0) == []                       # reported once
    replay(source[0], folder, cubes=slice(1, 2), speed=50)  # the next cube, whole
    follower.settle = 1.0
    assert follower.scan(121.0) == []                       # first seen: not still for 1 s yet
    events = follower.scan(122.5)
    assert [(type(e), e.cube.base) for e in events] == [(Complete, "sim_Pika_L_2")]
    assert events[0].cube.check.lines == 150
    # a recorder restarted under the same names writes over it: no longer complete, looked at again
    replay(source[0], folder, cubes=slice(1, 2), stop_after=(0, 0.3), speed=50)
    events = follower.scan(123.0)
    assert [type(e) for e in events] == [Changed] and events[0].cube.state == "growing"
    assert follower.scan(140.0)[0].why.startswith("incomplete for 17 s (sim_Pika_L_2.bil holds")
    # image sets of real recorder names (a new set is a new flight)
    assert image_set("Juvika_June2022_Pika_L_12") == "Juvika_June2022_Pika_L"
    assert image_set("20160228_17h18m_pika_L_1") == "20160228_17h18m_pika_L"
    assert image_set("manual_Pika_L_28") == "manual_Pika_L"


# ---- the live flight ----------------------------------------------------------------------------
def _tile_of(feature: dict, z: int = 21) -> tuple[int, int, int]:
    import mercantile

    w, s, e, n = feature["bbox"]
    t = mercantile.tile((w + e) / 2, (s + n) / 2, z)
    return t.z, t.x, t.y


def _truth_inside(truth, grid, d_px: float = 1.5) -> np.ndarray:
    """Tile pixels within d_px of the true footprint (dilated): where imagery may be."""
    from helpers import eroded_dilated

    return eroded_dilated(lambda e, n: truth.covered(e, n, crs="EPSG:3857"), grid, d_px)[1]


def test_live_flight_then_the_collection_of_a_plain_ingest(source, tmp_path):
    import zarr

    from archive.grid import tile_grid
    from archive.ingest.command import ingest

    src, truth = source
    folder, archive = tmp_path / "recorder", tmp_path / "archive"
    folder.mkdir()
    watcher = Watcher(str(folder), "--archive", str(archive), "--fov", str(FOV), "--idle", "2", "--settle", "0.2",
                      "--stall", "10", "--port", "0")
    url = watcher.url()
    closed: list = []
    writer = threading.Thread(target=lambda: closed.extend(replay(src, folder, gap_s=0.3)))
    writer.start()
    shown: dict[str, float] = {}   # cube id -> when a tile over it answered imagery
    features = {}
    while writer.is_alive() or len(shown) < len(truth.cubes):
        _, body, _ = get(url + "api/live")
        for flight in json.loads(body)["flights"]:
            for cid in flight["cube_ids"]:
                if cid in shown:
                    continue
                fc = json.loads(get(url + "api/collections")[1])
                feature = next(f for f in fc["features"] if f["id"] == cid)
                z, x, y = _tile_of(feature)
                status, planes, _ = get(f"{url}api/collections/{cid}/values/{z}/{x}/{y}?bands=0&mode=raw")
                assert status == 200, f"no imagery over listed cube {cid}"
                shown[cid] = time.time()
                features[cid] = feature
                values = np.frombuffer(planes, "<f4").reshape(256, 256)
                inside = _truth_inside(truth, tile_grid(z, x, y))
                assert np.isfinite(values).sum() > 1000
                assert not (np.isfinite(values) & ~inside).any(), f"{cid}: imagery outside the true footprint"
        assert watcher.proc.poll() is None, watcher.text()
        time.sleep(0.02)
    writer.join()
    latency = sorted(shown[next(i for i in shown if i.startswith(c.base + "-"))] - c.closed for c in closed)
    print(f"cube close -> listed with imagery: {', '.join(f'{v:.2f}' for v in latency)} s "
          f"(median {np.median(latency):.2f}, worst {latency[-1]:.2f})")
    assert len(closed) == len(truth.cubes) == len(shown)
    assert sum(f["properties"]["lines"] for f in features.values()) == sum(len(c.line_time) for c in truth.cubes)

    # one pass outline per true strip, each on that strip's true footprint (within half a pixel)
    done = watcher.wait_for("ingested as", timeout=90)
    # every cube was encoded as it closed and its chunks moved into the collection (nothing written twice)
    assert re.search(r"\(4 cubes; 4 encoded as they closed, 4 moved in, ", done), done
    deadline = time.monotonic() + 30
    while True:
        (flight,) = json.loads(get(url + "api/live")[1])["flights"]
        if flight["complete"] and not flight["cube_ids"] or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert flight["complete"] and flight["cubes"] == 4 and flight["lines"] == 600 and flight["status"] == "ingested"
    assert flight["cube_ids"] == []   # the collection shows instead of the cubes
    # the staged cubes served while recording are gone with them (no folder of links left behind)
    staged = archive / ".watch" / "cubes"
    assert not staged.exists() or not any(staged.iterdir()), sorted(staged.rglob("*"))[:5]
    assert len(flight["passes"]) == len(truth.strips)
    import shapely
    from pyproj import Transformer
    from shapely.geometry import Polygon, shape

    to_utm = Transformer.from_crs(4326, truth.epsg, always_xy=True)
    for drawn, true in zip(flight["passes"], truth.footprint(), strict=True):
        a = shapely.transform(shape(drawn), lambda xy: np.stack(to_utm.transform(xy[:, 0], xy[:, 1]), axis=1))
        b = Polygon(true)
        print(f"pass outline vs the true strip: {a.hausdorff_distance(b):.2f} m apart at most "
              f"(gsd {truth.nominal_gsd:.2f} m)")
        assert a.intersection(b).area / b.area > 0.99 and a.hausdorff_distance(b) < 0.5 * truth.nominal_gsd
    ids = [f["id"] for f in json.loads(get(url + "api/collections")[1])["features"]]
    assert ids == [flight["collection"]]
    assert watcher.stop() == 0 and watcher.lines[-1] == "archive watch: stopped"

    # the collection is a plain ingest of the finished folder: same values, attributes, Item
    (plain,) = ingest([str(folder)], tmp_path / "plain", FOV, progress=False)
    cid = flight["collection"]
    assert plain.cid == cid
    mine, theirs = (zarr.open_group(str(a / "collections" / f"{cid}.zarr"), mode="r") for a in (archive, tmp_path / "plain"))
    assert dict(mine.attrs) == dict(theirs.attrs)
    names = sorted(k for k, _ in theirs.arrays())
    assert sorted(k for k, _ in mine.arrays()) == names and "dn" in names
    for name in names:
        np.testing.assert_array_equal(mine[name][...], theirs[name][...], err_msg=name)
    items = [json.loads((a / "catalog" / "items" / f"{cid}.json").read_text()) for a in (archive, tmp_path / "plain")]
    assert items[0] == items[1]

    # a watch restarted on the folder lists and ingests nothing again
    stamp = (archive / "collections" / f"{cid}.zarr" / "zarr.json").stat().st_mtime_ns
    again = Watcher(str(folder), "--archive", str(archive), "--fov", str(FOV), "--idle", "0.5", "--settle", "0.1",
                    "--no-view")
    again.wait_for("following 1 folder")
    time.sleep(2)
    assert again.stop() == 0
    assert again.count("complete|ingest") == 0, again.text()
    assert (archive / "collections" / f"{cid}.zarr" / "zarr.json").stat().st_mtime_ns == stamp


# ---- faults -------------------------------------------------------------------------------------
def test_faults_one_line_each_and_sigterm_then_resume(source, tmp_path):
    from archive.collection import verify_store

    src, truth = source
    folder, usb, archive = tmp_path / "recorder", tmp_path / "usb", tmp_path / "archive"
    folder.mkdir()
    usb.mkdir()
    watcher = Watcher(str(folder), str(usb), "--archive", str(archive), "--fov", str(FOV), "--idle", "2",
                      "--settle", "0.1", "--stall", "1.5", "--no-view")
    watcher.wait_for("following 2 folders")
    replay(src, usb, cubes=slice(0, 1), speed=20)
    watcher.wait_for("usb/sim_Pika_L: cube sim_Pika_L_1 complete")
    os.rename(usb, tmp_path / "unplugged")                                  # the USB disk goes
    watcher.wait_for("usb: the folder is gone")
    replay(src, folder, cubes=slice(0, 2), speed=20)                         # two cubes, then the recorder dies
    replay(src, folder, cubes=slice(2, 3), stop_after=(0, 0.4), speed=20)   # ... in the third: no header, ever
    replay(src, folder, cubes=slice(2, 4), image_set="restart", speed=20, extras=False)   # restarted: a new set
    watcher.wait_for("cube sim_Pika_L_3 skipped: incomplete .*no header sim_Pika_L_3.bil.hdr")
    watcher.wait_for("recorder/restart: a new image set: a new flight")
    watcher.wait_for("recorder/sim_Pika_L: idle 2 s with 2 cubes: ingesting")
    assert watcher.stop() == 0                                               # SIGTERM while it ingests
    assert watcher.count("ingest stopped; the next watch resumes it") == 1, watcher.text()
    assert watcher.count("ingested as") == 0
    assert watcher.count("skipped") == 1 and watcher.count("folder is gone") == 1
    assert not list((archive / "catalog" / "items").glob("*.json")) if (archive / "catalog" / "items").exists() else True

    again = Watcher(str(folder), "--archive", str(archive), "--fov", str(FOV), "--idle", "1", "--settle", "0.1",
                    "--stall", "1", "--no-view", "--quiet", "--poll", "0.3")   # polling, as on a network mount
    again.wait_for(r"following 1 folder \(polling every 0.3 s\)")
    for name in ("sim_Pika_L", "restart"):
        again.wait_for(f"recorder/{name}: ingested as", timeout=120)
    assert again.stop() == 0, again.text()
    cids = [line.split(" as ")[1].split()[0] for line in again.lines if "ingested as" in line]
    assert len(set(cids)) == 2
    for cid in cids:
        assert verify_store(archive / "collections" / f"{cid}.zarr") == []
    items = sorted(p.stem for p in (archive / "catalog" / "items").glob("*.json"))
    assert items == sorted(cids)
    import zarr

    lines = [zarr.open_group(str(archive / "collections" / f"{c}.zarr"), mode="r")["dn"].shape[1] for c in cids]
    assert sorted(lines) == [300, 300]   # 2 cubes each: the truncated cube in neither
    assert truth.cubes[2].line_time.size == 150


# ---- the live page ------------------------------------------------------------------------------
def test_live_page_shows_the_cubes_appear(source, tmp_path):
    """The page in real Chromium, opened before the first cube: the cubes appear one after the other
    (their tiles asked and drawn), the pass outlines over them, the panel line counting them."""
    from PIL import Image
    import io

    chromium = Path("/usr/bin/chromium")
    if not chromium.exists():
        pytest.skip("Debian's chromium is not installed at /usr/bin/chromium")
    playwright = pytest.importorskip("playwright.sync_api")
    src, truth = source
    folder = tmp_path / "recorder"
    folder.mkdir()
    watcher = Watcher(str(folder), "--archive", str(tmp_path / "archive"), "--fov", str(FOV), "--idle", "600",
                      "--settle", "0.2", "--port", "0", "--quiet")
    url = watcher.url()
    with playwright.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(chromium), args=["--headless", "--no-sandbox", "--disable-gpu"])
        page = browser.new_page(viewport={"width": 900, "height": 700})
        errors, asked = [], []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on("request", lambda r: asked.append(r.url) if "/values" in r.url else None)
        page.goto(url)
        page.wait_for_function("() => window.viewer.booted && window.viewer.live !== null")
        writer = threading.Thread(target=replay, args=(src, folder), kwargs={"gap_s": 1.2})
        writer.start()
        counts = []
        while writer.is_alive() or not counts or counts[-1] < len(truth.cubes):
            n = page.evaluate("() => window.viewer.features.length")
            if not counts or n != counts[-1]:
                counts.append(n)
            assert watcher.proc.poll() is None, watcher.text()
            time.sleep(0.05)
        writer.join()
        assert counts[0] == 0 and counts[-1] == len(truth.cubes) and counts == sorted(counts) and len(counts) >= 3
        page.evaluate("() => window.viewer.map.fitBounds(window.viewer.footprints.getBounds(), {animate: false})")
        page.wait_for_function("() => window.viewer.settled && window.viewer.draws > 0", timeout=60_000)
        ids = page.evaluate("() => window.viewer.features.map((f) => f.id)")
        assert all(any(i in u for u in asked) for i in ids), "a listed cube's tiles were never asked"
        live = page.evaluate("() => window.viewer.live.flights[0]")
        assert len(live["passes"]) == len(truth.strips)   # each drawn, and the gaps' one (Multi)Polygon if any
        assert page.evaluate("() => document.querySelectorAll('.leaflet-live-pane path').length") == \
            len(truth.strips) + (1 if live["gaps"]["coordinates"] else 0)
        assert "4 cube(s), 600 lines, 2 pass(es)" in page.inner_text(".live-panel")
        page.evaluate("""() => { for (const s of ['.leaflet-control-container', '.leaflet-footprints-pane',
                                                  '.leaflet-tooltip-pane', '.leaflet-live-pane'])
                                   document.querySelector(s).style.display = 'none';
                                 document.getElementById('map').style.background = 'rgb(255,0,255)'; }""")
        shot = np.asarray(Image.open(io.BytesIO(page.locator("#map").screenshot())).convert("RGB"))
        assert (shot != np.array([255, 0, 255], np.uint8)).any(axis=-1).sum() > 5000   # imagery drawn
        assert not errors, errors
        browser.close()
    assert watcher.stop() == 0


def test_bad_input_is_one_line(tmp_path, capsys):
    import socket

    from archive.cli import main

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen(1)
    port = taken.getsockname()[1]
    base = [str(tmp_path / "rec"), "--archive", str(tmp_path / "archive"), "--fov", str(FOV)]
    for extra, words in ((["--port", str(port)], f"--port: cannot listen on 127.0.0.1:{port}"),
                         (["--calibration", str(tmp_path / "none.icp")], "--calibration"),
                         (["--fov", "0"], "--fov")):
        code = main(["watch", *base, *extra])
        err = capsys.readouterr().err
        assert code != 0 and words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    taken.close()
    code = main(["watch", str(tmp_path / "rec"), "--archive", "s3://bucket/archive", "--fov", str(FOV)])
    assert code != 0 and "local archive" in capsys.readouterr().err


def test_a_skipped_pass_is_a_gap(tmp_path):
    """Passes 1 and 3 of a three-pass flight (the middle one not flown): the ground of the middle
    pass between them is the gap, as the simulator's true footprints say."""
    import shapely
    from pyproj import Transformer
    from shapely.geometry import Polygon, shape
    from shapely.ops import unary_union

    from archive.simulator.command import simulate_flight
    from archive.watch.live import cube_feature, passes_and_gaps
    from archive.watch.stage import stage_links

    truth = simulate_flight(tmp_path / "flight", cubes=3, bands=2, samples=64, lines=400, cubes_per_pass=1, seed=7)
    features = [cube_feature(stage_links(tmp_path / "staged" / f"c{k}", [tmp_path / "flight" / f"sim_Pika_L_{k + 1}.bil"]),
                             FOV) for k in (0, 2)]
    passes, gaps = passes_and_gaps(features)
    assert len(passes) == 2
    to_utm = Transformer.from_crs(4326, truth.epsg, always_xy=True)
    gap = shapely.transform(shape(gaps), lambda xy: np.stack(to_utm.transform(xy[:, 0], xy[:, 1]), axis=1))
    rings = truth.footprint()   # per strip: the left edge first -> last line, then the right edge back

    def across(ring, reach=2.0):   # between the strip's first and last lines, each stretched 2 swaths out
        n = len(ring) // 2
        ends = []
        for left, right in ((ring[0], ring[-1]), (ring[n - 1], ring[n])):
            u = (right - left) * reach
            ends.append((left - u, right + u))
        return Polygon([ends[0][0], ends[0][1], ends[1][1], ends[1][0]])
    flown = unary_union([Polygon(rings[k]) for k in (0, 2)])
    true_gap = flown.convex_hull.difference(flown).intersection(across(rings[0])).intersection(across(rings[2]))
    missed = Polygon(rings[1]).intersection(true_gap)   # the middle pass's ground nobody imaged
    print(f"gap {gap.area:.0f} m2, true {true_gap.area:.0f} m2, the unflown pass's part {missed.area:.0f} m2")
    assert missed.area > 100
    assert gap.intersection(missed).area / missed.area > 0.97
    assert abs(gap.area - true_gap.area) / true_gap.area < 0.05


def test_a_live_cube_is_drawn_at_the_ground_height_given(tmp_path):
    """``watch --ground-height M``: a live cube's coverage is the ground its lines see at M (the simulator's
    true strip when M is the true ground), not the header's; 20 m higher ground, a narrower swath."""
    from pyproj import Transformer
    from shapely.geometry import Polygon, shape

    from archive.simulator.command import simulate_flight
    from archive.watch.command import _flat_ground
    from archive.watch.live import cube_feature
    from archive.watch.stage import stage_links

    truth = simulate_flight(tmp_path / "flight", cubes=1, bands=2, samples=64, lines=300, cubes_per_pass=1, seed=5)
    staged = stage_links(tmp_path / "staged" / "c0", [tmp_path / "flight" / "sim_Pika_L_1.bil"])
    to_utm = Transformer.from_crs(4326, truth.epsg, always_xy=True)

    def coverage(ground):
        ring = cube_feature(staged, FOV, ground)["properties"]["coverage"]["coordinates"][0]
        return Polygon([to_utm.transform(x, y) for x, y in ring])
    true = Polygon(truth.footprint()[0])
    at_truth = coverage(_flat_ground(str(truth.ground_height)))
    assert at_truth.hausdorff_distance(true) < 0.5 * truth.nominal_gsd
    higher = coverage(truth.ground_height + 20.0)
    assert cube_feature(staged, FOV, truth.ground_height + 20.0)["properties"]["ground_height"] == truth.ground_height + 20
    assert higher.area < 0.9 * true.area and higher.hausdorff_distance(true) > 5 * truth.nominal_gsd
    assert _flat_ground("auto") is None and _flat_ground(None) is None
