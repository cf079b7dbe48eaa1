"""Where the cores idle from process start to exit of one `archive render` (issue 37, part 2).

    python bench/timeline.py [--shape heldout|sidelap|tilted] [--cubes 8] [--bands 300] [--samples 900]
                             [--lines 1000] [--gsd 0.04] [--workdir DIR] [--format zarr|tif|hdr]
                             [--render-bands N] [--tmpfs] [--runs K] [--interval 0.1] [--json FILE]
                             [--render-option ARG ...]

Runs ``python -m archive render FLIGHT --out X ...`` as a user runs it (no ``--scheduler``: the
command starts its own LocalCluster; the flight of ``bench_outputs.py``'s ``--shape``, simulated once
into --workdir and reused) with ``ARCHIVE_TIMELINE`` set, so that the command appends its phases to a
file (:func:`archive.run.cluster.phase`: command parsed, pipeline imported, inputs opened and the cluster
wanted, cluster up, graph submitted, first and last writer task, the cluster's close started and
ended, output published, main returned, atexit handlers run), and samples every ``--interval`` s
(default 0.1):

- the machine's CPU split from ``/proc/stat`` (jiffies of all cores: user + nice + system + irq +
  softirq = busy, idle, iowait, steal);
- the process tree's CPU (``/proc/<pid>/stat`` of the command and every descendant: utime + stime +
  cutime + cstime, so that a child reaped meanwhile still counts), the command's own process apart.

It prints, per phase (between two consecutive marks, process start and exit included): wall, tree
CPU (command process / the rest: the scheduler and the nannies of a local cluster run in the command
process; the rest is the worker processes), **cores busy** = tree CPU / wall / cores, and what the
machine's cores did meanwhile: busy with other processes, **iowait** (idle with a task waiting on
the disk), idle, steal. Then the whole run: its wall, its exact tree CPU (``getrusage`` of the
reaped children), and cores x wall split into busy (ours), others, waiting on disk (iowait), idle
(what our code left idle: serial phases) and steal; with ``--runs`` K > 1, the medians per phase and
of the whole runs. ``--tmpfs`` writes the output under ``/dev/shm`` (checked against the memory
available first) so that the disk is out of the picture; ``--render-bands N`` renders the first N
bands only (the held-out shape at 100 bands: ~2.4 GB). The output is deleted after each run.

The machine may be shared: other processes' CPU shows as "others"; wall and idle are then polluted,
the structure (phases, one-core phases, the tail) still shows.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (flights, load)

HZ = os.sysconf("SC_CLK_TCK")

#: What the command did up to each mark (the phase that ends there).
PHASES = {
    "command": "interpreter start, CLI imports, options parsed",
    "imports": "pipeline imports (workers starting in a thread)",
    "cluster-wanted": "options checked, inputs opened",
    "cluster-up": "the local cluster's start, its end",
    "graph-submit": "plan and graph built, submitted",
    "first-write": "to the first writer task's end",
    "last-write": "the task stream, to the last writer's end",
    "cluster-close": "renderers asked; the cluster's close started (a thread)",
    "cluster-closed": "the close's end (publish goes on beside it)",
    "published": "publish (ENVI header, COG layout, rename, STAC Item), close joined",
    "main-returned": "summary printed",
    "atexit-done": "threads joined, atexit handlers run",
    "exit": "interpreter exit (finalization; os._exit since issue 37)",
}


def machine_jiffies() -> dict:
    """Jiffies of all cores since boot from the first line of /proc/stat: busy (user + nice + system
    + irq + softirq), idle, iowait, steal."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    user, nice, system, idle, iowait, irq, softirq, steal = (v + [0] * 8)[:8]
    return {"busy": user + nice + system + irq + softirq, "idle": idle, "iowait": iowait, "steal": steal}


def _proc_stats() -> dict[int, tuple[int, int, int]]:
    """pid -> (ppid, utime + stime + cutime + cstime jiffies, utime + stime jiffies) of every process now."""
    out = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                rest = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        # after 'pid (comm)': state ppid ... utime(12) stime(13) cutime(14) cstime(15) (0-based in rest)
        own = int(rest[11]) + int(rest[12])
        out[int(name)] = (int(rest[1]), own + int(rest[13]) + int(rest[14]), own)
    return out


def tree_jiffies(root: int) -> tuple[int, int]:
    """(the root's own, the whole tree's) CPU jiffies: the root's utime + stime (its threads: the
    command, the scheduler of a local cluster); utime + stime + cutime + cstime of ``root`` and of
    every live descendant."""
    stats = _proc_stats()
    children: dict[int, list[int]] = {}
    for pid, (ppid, _, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        if pid in stats:
            total += stats[pid][1]
            todo += children.get(pid, [])
    return stats.get(root, (0, 0, 0))[2], total


class Sampler:
    """Samples :func:`machine_jiffies` and :func:`tree_jiffies` of ``root`` every ``interval`` s in a
    thread: rows (epoch s, machine dict, root jiffies, tree jiffies), the tree's made monotonic
    (a child reaped between two reads must not take CPU back)."""

    def __init__(self, root: int, interval: float):
        self.root, self.interval = root, interval
        self.rows: list[tuple[float, dict, int, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def sample(self) -> None:
        t, m = time.time(), machine_jiffies()
        own, tree = tree_jiffies(self.root)
        if self.rows:
            own, tree = max(own, self.rows[-1][2]), max(tree, self.rows[-1][3])
        self.rows.append((t, m, own, tree))

    def _run(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.interval)

    def __enter__(self) -> Sampler:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def read_marks(path: Path) -> list[tuple[str, float]]:
    """The ``NAME SECONDS`` lines of an ``ARCHIVE_TIMELINE`` file, in time order; a name seen more
    than once (a batch's several graphs) keeps its first time, except 'last-write' (its last)."""
    marks: dict[str, float] = {}
    for line in path.read_text().splitlines() if path.exists() else []:
        name, t = line.split()
        if name not in marks or name == "last-write":
            marks[name] = float(t)
    return sorted(marks.items(), key=lambda kv: kv[1])


def run_timeline(cmd: list[str], interval: float = 0.1, env: dict | None = None) -> dict:
    """Run ``cmd`` (an ``archive render`` command line) with ``ARCHIVE_TIMELINE`` set and sample it;
    the result: start and exit (epoch s), marks, samples, exact tree CPU-s (``getrusage`` of the
    reaped children), return code, stderr's tail, cores, load before and after."""
    with tempfile.TemporaryDirectory(prefix="archive-timeline-") as d:
        marks_file = Path(d) / "marks.txt"
        env = {**os.environ, **(env or {}), "ARCHIVE_TIMELINE": str(marks_file)}
        load0 = br.load()
        ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.time()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        with Sampler(proc.pid, interval) as sampler:
            _, stderr = proc.communicate()
            end = time.time()
        ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        marks = read_marks(marks_file)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    rows = [(t, m, own, tree) for t, m, own, tree in sampler.rows if t <= end]
    last = sampler.rows[-1]
    rows.append((end, last[1], last[2], max(last[3], round(cpu * HZ))))   # the exact total at exit
    return {"cmd": cmd, "start": start, "end": end, "marks": marks, "rows": rows, "tree_cpu_s": cpu,
            "returncode": proc.returncode, "stderr": stderr[-3000:], "cores": os.cpu_count() or 1,
            "load": [load0, br.load()]}


def _at(rows, t: float, key) -> float:
    """A cumulative quantity ``key(row)`` at time ``t``, linearly between the samples around it."""
    if t <= rows[0][0]:
        return key(rows[0])
    for a, b in zip(rows, rows[1:]):
        if t <= b[0]:
            f = (t - a[0]) / max(b[0] - a[0], 1e-9)
            return key(a) + f * (key(b) - key(a))
    return key(rows[-1])


KEYS = {"tree": lambda r: r[3] / HZ, "own": lambda r: r[2] / HZ,
        **{k: (lambda r, k=k: r[1][k] / HZ) for k in ("busy", "idle", "iowait", "steal")}}


def split(R: dict, t0: float, t1: float) -> dict:
    """What the cores did between epoch seconds ``t0`` and ``t1``: wall, tree CPU-s (the command
    process's and the rest's), cores busy, and the cores x wall split into ours, others, iowait,
    idle, steal (fractions; measured machine-wide, so they sum to ~1)."""
    d = {k: _at(R["rows"], t1, f) - _at(R["rows"], t0, f) for k, f in KEYS.items()}
    wall = max(t1 - t0, 1e-9)
    total = max(d["busy"] + d["idle"] + d["iowait"] + d["steal"], 1e-9)   # ~ cores x wall
    ours = min(d["tree"], d["busy"]) if d["busy"] > 0 else d["tree"]
    return {"wall_s": t1 - t0, "tree_cpu_s": d["tree"], "command_cpu_s": d["own"], "rest_cpu_s": d["tree"] - d["own"],
            "busy": d["tree"] / wall / R["cores"], "ours": ours / total, "others": max(d["busy"] - ours, 0) / total,
            "iowait": d["iowait"] / total, "idle": d["idle"] / total, "steal": d["steal"] / total}


def phases(R: dict) -> list[dict]:
    """:func:`split` of every phase: from process start through the marks (in time order) to exit."""
    points = [("start", R["start"]), *[(n, t) for n, t in R["marks"] if R["start"] <= t <= R["end"]], ("exit", R["end"])]
    out = []
    for (a, ta), (b, tb) in zip(points, points[1:]):
        out.append({"from": a, "to": b, "at_s": tb - R["start"], "what": PHASES.get(b, b), **split(R, ta, tb)})
    return out


def report(R: dict) -> list[str]:
    """Markdown: the phase table, then the whole run's split."""
    rows = ["| phase (ends at) | what | ends at s | wall s | tree CPU-s (command / rest) | cores busy | "
            "others | iowait | idle |", "|---|---|---|---|---|---|---|---|---|"]
    for p in R["phases"]:
        rows.append(f"| {p['to']} | {p['what']} | {p['at_s']:.2f} | {p['wall_s']:.2f} | {p['tree_cpu_s']:.2f} "
                    f"({p['command_cpu_s']:.2f} / {p['rest_cpu_s']:.2f}) | {100 * p['busy']:.0f} % | "
                    f"{100 * p['others']:.0f} % | {100 * p['iowait']:.0f} % | {100 * p['idle']:.0f} % |")
    w = R["whole"]
    rows += ["", f"whole run: {w['wall_s']:.2f} s, {R['tree_cpu_s']:.2f} CPU-s (tree, getrusage), cores busy "
             f"**{100 * R['tree_cpu_s'] / w['wall_s'] / R['cores']:.0f} %**; of {R['cores']} cores x wall: busy (ours) "
             f"{100 * w['ours']:.0f} %, others {100 * w['others']:.0f} %, waiting on disk (iowait) "
             f"{100 * w['iowait']:.0f} %, idle (serial phases of our code) {100 * w['idle']:.0f} %, steal "
             f"{100 * w['steal']:.0f} %; load {R['load'][0]} -> {R['load'][1]}"]
    return rows


def summary(results: list[dict]) -> list[str]:
    """Markdown: per phase (by its end mark) the median wall and cores busy over several runs, and
    the whole runs' medians."""
    import statistics

    names = list(dict.fromkeys(p["to"] for R in results for p in R["phases"]))
    rows = [f"median of {len(results)} runs:", "",
            "| phase (ends at) | wall s | cores busy | iowait | idle |", "|---|---|---|---|---|"]
    for name in names:
        ps = [p for R in results for p in R["phases"] if p["to"] == name]
        rows.append(f"| {name} | {statistics.median(p['wall_s'] for p in ps):.2f} | "
                    f"{100 * statistics.median(p['busy'] for p in ps):.0f} % | "
                    f"{100 * statistics.median(p['iowait'] for p in ps):.0f} % | "
                    f"{100 * statistics.median(p['idle'] for p in ps):.0f} % |")
    med = {k: statistics.median(R["whole"][k] for R in results) for k in ("ours", "others", "iowait", "idle", "steal")}
    rows += ["", f"whole run: {statistics.median(R['end'] - R['start'] for R in results):.2f} s, "
             f"{statistics.median(R['tree_cpu_s'] for R in results):.2f} CPU-s, cores busy "
             f"**{100 * statistics.median(R['busy'] for R in results):.0f} %**; busy (ours) {100 * med['ours']:.0f} %, "
             f"others {100 * med['others']:.0f} %, iowait {100 * med['iowait']:.0f} %, idle {100 * med['idle']:.0f} %, "
             f"steal {100 * med['steal']:.0f} %"]
    return rows


def analyse(R: dict) -> dict:
    """``R`` (from :func:`run_timeline`) with its phases and whole-run split added."""
    R["phases"] = phases(R)
    R["whole"] = split(R, R["start"], R["end"])
    R["busy"] = R["tree_cpu_s"] / max(R["end"] - R["start"], 1e-9) / R["cores"]
    return R


def tmpfs_folder(need: int) -> Path:
    """A fresh folder under /dev/shm for an output of ``need`` bytes; SystemExit (one line, with the
    fix) when /dev/shm or the memory available holds less than 1.5 x that."""
    avail = 0
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            avail = int(line.split()[1]) * 1024
    free = shutil.disk_usage("/dev/shm").free
    if min(avail, free) < 1.5 * need:
        raise SystemExit(f"timeline.py: --tmpfs: the output needs {need / 1e9:.1f} GB and /dev/shm has "
                         f"{free / 1e9:.1f} GB free, {avail / 1e9:.1f} GB of memory available; give fewer "
                         "--render-bands or drop --tmpfs")
    return Path(tempfile.mkdtemp(prefix="archive-timeline-", dir="/dev/shm"))


def render_command(flight: Path, out: Path, gsd: float, ground: float | str, bands: int | None, extra=()) -> list[str]:
    """``python -m archive render`` as a user runs it (``bench_outputs.render_plain``'s options):
    ``gsd`` and ``ground`` (the ground's height, or 'auto') in metres, the first ``bands`` bands
    (None: all)."""
    chosen = "all" if not bands else ",".join(str(b) for b in range(bands))
    return [sys.executable, "-m", "archive", "render", str(flight), "--fov", str(br.FOV), "--gsd", str(gsd),
            "--ground-height", str(ground), "--mode", br.MODE, "--bands", chosen, "--out", str(out), "--overwrite",
            "--quiet", *extra]


def _remove(out: Path) -> None:
    for f in (out, out.with_suffix(""), Path(str(out) + ".json")):
        if f.is_dir():
            shutil.rmtree(f, ignore_errors=True)
        elif f.exists():
            f.unlink()


def main(argv=None) -> int:
    from bench_outputs import SHAPES, output_bytes

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    br.add_flight_arguments(ap, bands=300, workdir="/tmp/archive-bench-outputs", cubes=8)
    ap.add_argument("--shape", choices=sorted(SHAPES), default="heldout", help="flight shape (bench_outputs.py's)")
    ap.add_argument("--flight", metavar="DIR", help="render this flight instead of the simulated --shape "
                    "(its ground at the simulator's height)")
    ap.add_argument("--format", choices=["zarr", "tif", "hdr"], default="zarr")
    ap.add_argument("--render-bands", type=int, metavar="N", help="render the first N bands only (default: all)")
    ap.add_argument("--tmpfs", action="store_true", help="write the output under /dev/shm (the disk out of the picture)")
    ap.add_argument("--runs", type=int, default=1, help="runs, one after the other (default 1)")
    ap.add_argument("--interval", type=float, default=0.1, help="seconds between samples (default 0.1)")
    ap.add_argument("--render-option", action="append", default=[], metavar="ARG",
                    help="one more argument for archive render (repeat it)")
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    args.heading, args.spacing = SHAPES[args.shape]
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    flight = Path(args.flight) if args.flight else br.flight_dir(args)
    br.warm(flight)
    from archive.simulator.command import GROUND_HEIGHT

    bands = args.render_bands or None
    folder = work
    if args.tmpfs:
        _, plan, _ = br.make_plan(flight, args.gsd, GROUND_HEIGHT)
        folder = tmpfs_folder(plan.grid.width * plan.grid.height * (bands or plan.nbands) * 4)
    results = []
    try:
        for k in range(args.runs):
            out = folder / f"timeline.{args.format}"
            cmd = render_command(flight, out, args.gsd, GROUND_HEIGHT, bands, args.render_option)
            try:
                R = run_timeline(cmd, args.interval)
            finally:
                size = output_bytes(out) if out.exists() else None
                _remove(out)
            if R["returncode"] != 0:
                raise SystemExit(f"{' '.join(cmd)} failed ({R['returncode']}): {R['stderr']}")
            analyse(R)
            R["out_bytes"] = size
            print(f"\nrun {k + 1} of {args.runs}: archive render {' '.join(cmd[4:])}", flush=True)
            print("\n".join(report(R)), flush=True)
            results.append({k2: v for k2, v in R.items() if k2 != "rows"})
    finally:
        if args.tmpfs:
            shutil.rmtree(folder, ignore_errors=True)
    if len(results) > 1:
        print("\n" + "\n".join(summary(results)), flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
