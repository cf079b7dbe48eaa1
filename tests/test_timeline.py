"""``ARCHIVE_TIMELINE`` (issue 37): the phases ``archive render`` records (:func:`archive.run.cluster.phase`)
when run as a user runs it, what ``bench/timeline.py`` makes of them and of its CPU samples, and the
command's exit through :func:`archive.cli.exit_now` (the interpreter's finalization skipped, nothing
else: atexit handlers run, no worker left behind)."""

from __future__ import annotations

import json
import sys
import time
import uuid
from pathlib import Path

import psutil

from archive.run.cluster import phase

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import timeline  # noqa: E402  (bench/timeline.py)

#: The marks of one local render, in the order they must come (cluster-up may come anywhere after
#: the command started and before the graph is submitted: it is a thread's).
ORDER = ["command", "imports", "cluster-wanted", "graph-submit", "first-write", "last-write", "cluster-close",
         "published", "main-returned", "atexit-done"]


def _with_token(token: str) -> list[psutil.Process]:
    """Live processes whose environment holds ``ARCHIVE_TEST_TOKEN=token`` (the command's tree)."""
    found = []
    for p in psutil.process_iter():
        try:
            if p.environ().get("ARCHIVE_TEST_TOKEN") == token and p.status() != psutil.STATUS_ZOMBIE:
                found.append(p)
        except psutil.Error:
            continue
    return found


def test_a_render_run_as_a_program_records_its_phases_and_leaves_nothing(small_flight, tmp_path):
    out = tmp_path / "m.zarr"
    # --workers: a flight this small would otherwise render in this process (run.command.small_job);
    # the phases asked for here are the local cluster's
    cmd = timeline.render_command(small_flight, out, 0.05, "auto", None, extra=("--workers", "2"))
    token = uuid.uuid4().hex
    R = timeline.analyse(timeline.run_timeline(cmd, interval=0.05, env={"ARCHIVE_TEST_TOKEN": token}))
    assert R["returncode"] == 0, R["stderr"]
    assert json.loads(Path(str(out) + ".json").read_text())["properties"]["archive:recipe"]
    names = [n for n, _ in R["marks"]]
    assert [n for n in names if n in ORDER] == ORDER, names
    assert names.index("command") < names.index("cluster-up") < names.index("graph-submit")
    assert all(R["start"] <= t <= R["end"] for _, t in R["marks"])
    # the phases tile the run: start, every mark, exit
    walls = [p["wall_s"] for p in R["phases"]]
    assert R["phases"][0]["from"] == "start" and R["phases"][-1]["to"] == "exit"
    assert abs(sum(walls) - (R["end"] - R["start"])) < 1e-6 and min(walls) >= 0
    # the sampled tree CPU ends at the exact total (getrusage of the reaped tree), which is real work
    assert R["tree_cpu_s"] > 0.5 and abs(sum(p["tree_cpu_s"] for p in R["phases"]) - R["tree_cpu_s"]) < 0.05
    w = R["whole"]
    assert abs(w["ours"] + w["others"] + w["iowait"] + w["idle"] + w["steal"] - 1) < 1e-6
    # the worker processes ended with the command (they carry its environment)
    deadline = time.monotonic() + 10
    while _with_token(token) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _with_token(token) == []


def test_phase_writes_only_when_asked_and_never_raises(tmp_path, monkeypatch):
    path = tmp_path / "marks.txt"
    monkeypatch.delenv("ARCHIVE_TIMELINE", raising=False)
    phase("nothing")
    assert not path.exists()
    monkeypatch.setenv("ARCHIVE_TIMELINE", str(path))
    before = time.time()
    phase("one")
    phase("two")
    (n1, t1), (n2, t2) = (line.split() for line in path.read_text().splitlines())
    assert (n1, n2) == ("one", "two") and before - 1 <= float(t1) <= float(t2) <= time.time() + 1
    monkeypatch.setenv("ARCHIVE_TIMELINE", str(tmp_path))   # a folder: not writable as a file
    phase("three")


def test_split_of_known_samples():
    """Two cores for 4 s: the tree used 3 CPU-s (1 in its own process), others 1, iowait 2, idle 2;
    a phase of the first half gets half of each (linear between samples)."""
    hz = timeline.HZ

    def row(t: float, busy: float, idle: float, iowait: float, own: float, tree: float):
        return (t, {"busy": round(busy * hz), "idle": round(idle * hz), "iowait": round(iowait * hz), "steal": 0},
                round(own * hz), round(tree * hz))

    R = {"rows": [row(100.0, 0, 0, 0, 0, 0), row(104.0, 4, 2, 2, 1, 3)], "cores": 2, "start": 100.0, "end": 104.0,
         "marks": [("half", 102.0)], "tree_cpu_s": 3.0}
    timeline.analyse(R)
    w = R["whole"]
    assert abs(w["ours"] - 3 / 8) < 1e-9 and abs(w["others"] - 1 / 8) < 1e-9
    assert abs(w["iowait"] - 0.25) < 1e-9 and abs(w["idle"] - 0.25) < 1e-9
    assert abs(R["busy"] - 3 / 4 / 2) < 1e-9
    first, second = R["phases"]
    assert (first["from"], first["to"], second["to"]) == ("start", "half", "exit")
    assert abs(first["tree_cpu_s"] - 1.5) < 1e-9 and abs(first["command_cpu_s"] - 0.5) < 1e-9
    assert abs(first["busy"] - 1.5 / 2 / 2) < 1e-9 and abs(second["iowait"] - 0.25) < 1e-9
