"""Benchmark of `archive render` (issue 4): ours vs GDAL's direct method vs the bare I/O floor.

    python bench/bench_render.py [--cubes N] [--bands B] [--samples S] [--lines L] [--gsd 0.04]
                                 [--workdir DIR] [--keep] [--gdal-group G] [--json FILE]

Defaults are the paper shape: 2 cubes of 900 samples x 1000 lines x 300 bands (uint16 BIL,
540 MB each), rendered at 4 cm with all bands, radiance mode. One run measures, on the same
simulated flight (simulated once into --workdir and reused while its marker file exists):

1. ours, end-to-end: ``archive.georectify([FLIGHT], "X.zarr", ...)`` (what ``archive render`` runs) in a
   subprocess (Dask local cluster, Zarr writer included); peak memory = max over time of the summed
   RSS of the whole process tree (Dask nanny + worker included), polled every 0.1 s with psutil,
   and the largest single process (``/usr/bin/time -v``).
2. ours, render core: in-process, on the plan ``archive.api.plan`` makes (the one ``archive.georectify``
   renders), per cube: ``rasterize_lookup`` once on the cube's window of the output grid, then per group of 32 bands (the pipeline's task size): read bands + radiometry,
   ``render_lookup`` (8 bands per GL pass), write into a .npy memmap (flushed).
3. GDAL direct method: ``rasterio.warp.reproject(src_geoloc_array=(X, Y), nearest)`` per cube
   and group of ``--gdal-group`` bands, same grid windows, same radiometry applied in numpy first,
   same memmap writing. Geolocation arrays: see :func:`geolocation`.
4. I/O floor: read every input .bil once (np.fromfile) + write the mosaic's float32 byte count once,
   fsync'ed.

Every method runs with the input already in the page cache (dropping caches needs root): the
script reads the .bil files once before timing anything. Prints a Markdown table and ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

FOV = 47.5
MODE = "radiance"
MB = 1e6


# ---------------------------------------------------------------------------------------------
# Machine, load and memory
# ---------------------------------------------------------------------------------------------
def machine() -> dict:
    cpu = "?"
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    mem = 0
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal"):
            mem = int(line.split()[1]) * 1024
    return {"cpu": cpu, "cores": os.cpu_count(), "ram_gb": round(mem / 1e9, 1),
            "python": platform.python_version(), "kernel": platform.release(), "page_reclaim": page_reclaim()}


def page_reclaim() -> list[str]:
    """What the machine does to memory behind a benchmark's back, which makes its I/O and CPU figures
    vary from run to run (bench/RESULTS.md, issue 37): a DAMON scheme paging out what was not
    accessed lately ("DAMON pageout": it drops page-cache folios, the input's among them, whatever
    the free memory) and a virtio balloon reporting free pages to the host ("balloon free page
    reporting": a page touched again is faulted in by the host first). Empty where neither is on or
    they cannot be read."""
    found = set()
    try:
        for action in Path("/sys/kernel/mm/damon/admin/kdamonds").glob("*/contexts/*/schemes/*/action"):
            if action.read_text().strip() == "pageout" and \
                    (action.parents[4] / "state").read_text().strip() == "on":
                found.add("DAMON pageout")
        for features in Path("/sys/bus/virtio/drivers/virtio_balloon").glob("virtio*/features"):
            bits = features.read_text().strip()   # bit 5: VIRTIO_BALLOON_F_REPORTING
            if len(bits) > 5 and bits[5] == "1":
                found.add("balloon free page reporting")
    except OSError:
        pass
    return sorted(found)


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


class MemoryPoll:
    """Polls the summed RSS of a process tree (pid and all descendants) in a thread.

    peak_rss: max over time of sum(rss); peak_anon: same for rss - shared (file-backed pages, e.g.
    memory-mapped input, excluded), bytes; cpu_s: CPU-seconds of the tree's processes.
    """

    def __init__(self, pid: int | None = None, interval: float = 0.1):
        import psutil

        self.proc = psutil.Process(pid or os.getpid())
        self.interval = interval
        self.peak_rss = 0
        self.peak_anon = 0
        self._cpu: dict[int, float] = {}   # pid -> user + system CPU-s last seen
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        import psutil

        rss = anon = 0
        try:
            procs = [self.proc, *self.proc.children(recursive=True)]
        except psutil.Error:
            return
        for p in procs:
            try:
                m = p.memory_info()
            except psutil.Error:
                continue
            rss += m.rss
            anon += m.rss - m.shared
            try:
                t = p.cpu_times()
                self._cpu[p.pid] = t.user + t.system
            except psutil.Error:
                pass
        self.peak_rss = max(self.peak_rss, rss)
        self.peak_anon = max(self.peak_anon, anon)

    @property
    def cpu_s(self) -> float:
        """CPU-seconds of the tree's processes as last seen (polled: a process's last 0.1 s may be
        missed)."""
        return sum(self._cpu.values())

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.interval)

    def __enter__(self) -> MemoryPoll:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


# ---------------------------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------------------------
def add_flight_arguments(ap: argparse.ArgumentParser, bands: int, workdir: str, *, cubes: int = 2,
                         samples: int | None = 900, lines: int = 1000, gsd: float = 0.04) -> None:
    """The options of the simulated flight (--cubes, --bands, --samples, --lines), --gsd (metres) and
    --workdir, with these defaults (samples None: no --samples, the bench fixes it)."""
    ap.add_argument("--cubes", type=int, default=cubes, help=f"cubes of the simulated flight (default {cubes})")
    ap.add_argument("--bands", type=int, default=bands, help=f"bands per cube (default {bands})")
    if samples is not None:
        ap.add_argument("--samples", type=int, default=samples, help=f"samples per line (default {samples})")
    ap.add_argument("--lines", type=int, default=lines, help=f"lines per cube (default {lines})")
    ap.add_argument("--gsd", type=float, default=gsd, help=f"output pixel size, metres (default {gsd:g})")
    ap.add_argument("--workdir", default=workdir, help=f"where the flight and outputs go (default {workdir})")


def flight_dir(args, prefix: str = "flight_") -> Path:
    """Simulate the flight into --workdir once; reuse it while its completion marker exists.

    ``args.heading`` (degrees, grid heading of the passes) and ``args.spacing`` (metres between
    passes) and ``args.cubes_per_pass`` (default 2), when the parser has them and they differ from the simulator's defaults, go into the
    directory's name and the simulation (the spacing by the simulator's ``SPACING`` constant, set
    only while this flight is simulated)."""
    from archive.simulator import command

    heading = getattr(args, "heading", None)
    spacing = getattr(args, "spacing", None)
    name = f"{prefix}c{args.cubes}_b{args.bands}_s{args.samples}_l{args.lines}"
    if heading is not None and heading != command.HEADING_DEG:
        name += f"_h{heading:g}"
    if spacing is not None and spacing != command.SPACING:
        name += f"_p{spacing:g}"
    d = Path(args.workdir) / name
    marker = d / ".bench-complete"
    if marker.exists():
        print(f"reusing simulated flight {d} (marker {marker.name})", flush=True)
        return d
    if d.exists():
        shutil.rmtree(d)
    print(f"simulating {args.cubes} cube(s) of {args.samples} x {args.lines} x {args.bands} into {d}", flush=True)
    t = time.perf_counter()
    default_spacing = command.SPACING
    try:
        if spacing is not None:
            command.SPACING = float(spacing)
        command.simulate_flight(d, cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines,
                                cubes_per_pass=getattr(args, "cubes_per_pass", 2), seed=1, progress=True,
                                heading_deg=command.HEADING_DEG if heading is None else float(heading))
    finally:
        command.SPACING = default_spacing
    marker.write_text(f"{time.perf_counter() - t:.1f} s\n")
    return d


def bil_files(flight: Path) -> list[Path]:
    return sorted(flight.glob("*.bil"))


def warm(flight: Path) -> float:
    """Read every .bil once so that all methods start from a warm page cache; seconds."""
    t = time.perf_counter()
    for f in bil_files(flight):
        with open(f, "rb") as fh:
            while fh.read(64 << 20):
                pass
    return time.perf_counter() - t


# ---------------------------------------------------------------------------------------------
# 4. I/O floor
# ---------------------------------------------------------------------------------------------
def io_floor(flight: Path, out_bytes: int, work: Path) -> dict:
    t0 = time.perf_counter()
    nread = 0
    for f in bil_files(flight):
        nread += np.fromfile(f, dtype=np.uint8).nbytes
    t1 = time.perf_counter()
    block = np.zeros(64 << 20, np.uint8)  # 64 MiB
    path = work / "floor.bin"
    with open(path, "wb") as fh:
        left = out_bytes
        while left > 0:
            n = min(left, block.nbytes)
            fh.write(memoryview(block)[:n])
            left -= n
        fh.flush()
        os.fsync(fh.fileno())
    t2 = time.perf_counter()
    path.unlink()
    return {"read_s": t1 - t0, "write_s": t2 - t1, "wall_s": t2 - t0, "read_mb": nread / MB,
            "write_mb": out_bytes / MB}


# ---------------------------------------------------------------------------------------------
# 1. End-to-end
# ---------------------------------------------------------------------------------------------
def end_to_end(flight: Path, args, work: Path, ground: float, tag: str = "e2e") -> dict:
    out = work / f"{tag}.zarr"
    call = (f"archive.georectify([{str(flight)!r}], {str(out)!r}, gsd={args.gsd!r}, fov={FOV!r}, "
            f"ground_height={ground!r}, mode={MODE!r}, overwrite=True)")
    code = f"import json, archive\nprint(json.dumps({call}))"
    cmd = [sys.executable, "-c", code]
    timev = shutil.which("time") or ("/usr/bin/time" if Path("/usr/bin/time").exists() else None)
    full = ([timev, "-v"] if timev else []) + cmd
    print(f"$ python -c '{call}'", flush=True)
    env = dict(os.environ)
    t = time.perf_counter()
    proc = subprocess.Popen(full, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    with MemoryPoll(proc.pid) as poll:
        stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        print(stderr[-4000:], file=sys.stderr)
        raise SystemExit(f"archive.render failed with exit code {proc.returncode}")
    largest = None
    for line in stderr.splitlines():
        if "Maximum resident set size" in line:
            largest = int(line.split(":")[1]) * 1024
    summary = json.loads(stdout.strip().splitlines()[-1])
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    return {"cmd": call, "wall_s": wall, "peak_tree_rss": poll.peak_rss,
            "peak_tree_anon": poll.peak_anon, "largest_process_rss": largest, "zarr_mb": size / MB,
            "summary": summary, "graph_s": summary["graph_seconds"], "out": str(out)}


def one_cube_flight(flight: Path, work: Path) -> Path:
    """A flight directory holding only the first cube (symlinks), for memory-vs-length scaling."""
    d = work / "flight_first_cube"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    first = bil_files(flight)[0]
    base = first.name[: -len(".bil")]
    for f in flight.iterdir():
        if f.name.startswith(base + ".") or f.suffix == ".icp":
            (d / f.name).symlink_to(f)
    return d


# ---------------------------------------------------------------------------------------------
# Plan (shared by 2 and 3): the library's plan, the same grid and cube windows as the pipeline
# ---------------------------------------------------------------------------------------------
def make_plan(flight: Path, gsd: float, ground: float):
    """(source, plan, seconds): the plan ``archive.georectify`` renders (sources opened, cube meshes,
    grid, windows; no GL), and the seconds it took (mostly the meshes)."""
    from archive.api import plan

    t = time.perf_counter()
    planned = plan([flight], gsd=gsd, fov=FOV, ground_height=ground, mode=MODE)
    mesh_s = time.perf_counter() - t
    return planned.sources[0], planned.plan, mesh_s


def out_memmap(path: Path, shape) -> np.ndarray:
    return np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=shape)


# ---------------------------------------------------------------------------------------------
# 2. Render core
# ---------------------------------------------------------------------------------------------
def render_core(source, plan, mesh_s: float, work: Path, group: int = 32) -> dict:
    from tqdm import tqdm

    from archive.render.context import get_context
    from archive.render.renderer import rasterize_lookup, render_lookup

    get_context()  # context creation is not part of the per-cube cost
    per_cube = []
    with MemoryPoll() as poll:
        for job in plan.jobs:
            c, win = job.cube, job.window
            nb = source.cubes[c].bands
            out = out_memmap(work / f"core_cube{c}.npy", (nb, win.height, win.width))
            t_read = t_render = t_write = 0.0
            t0 = time.perf_counter()
            lookup = rasterize_lookup(job.mesh, win, source.cubes[c].samples)
            t_lookup = time.perf_counter() - t0
            for b0 in tqdm(range(0, nb, group), desc=f"core cube {c}", unit="group", leave=False):
                idx = list(range(b0, min(b0 + group, nb)))
                t = time.perf_counter()
                dn = source.read_bands(c, idx)
                rad = source.radiometry(c, idx, MODE)
                t_read += time.perf_counter() - t
                t = time.perf_counter()
                res = render_lookup(lookup, dn, rad, bands_per_pass=min(8, len(idx)))
                t_render += time.perf_counter() - t
                t = time.perf_counter()
                out[b0:b0 + len(idx)] = res.values
                t_write += time.perf_counter() - t
            t = time.perf_counter()
            out.flush()
            del out
            t_write += time.perf_counter() - t
            wall = time.perf_counter() - t0 + mesh_s / len(plan.jobs)
            per_cube.append({"cube": c, "window": [win.height, win.width], "bands": nb, "wall_s": wall,
                             "read_s": t_read, "lookup_s": t_lookup, "render_s": t_render, "write_s": t_write,
                             "mesh_s": mesh_s / len(plan.jobs),
                             "mpx_band_per_s": win.height * win.width * nb / 1e6 / wall})
    return {"per_cube": per_cube, "wall_s": sum(p["wall_s"] for p in per_cube),
            "peak_rss": poll.peak_rss, "peak_anon": poll.peak_anon}


def profile_render(source, plan, bands: int = 32) -> str:
    """cProfile of render_lookup on the first cube, ``bands`` bands, 8 per pass: where time goes."""
    import cProfile
    import io
    import pstats

    from archive.render.renderer import rasterize_lookup, render_lookup

    job = plan.jobs[0]
    nb = min(bands, source.cubes[job.cube].bands)
    idx = list(range(nb))
    dn, rad = source.read_bands(job.cube, idx), source.radiometry(job.cube, idx, MODE)
    lookup = rasterize_lookup(job.mesh, job.window, source.cubes[job.cube].samples)
    prof = cProfile.Profile()
    prof.enable()
    render_lookup(lookup, dn, rad, 8)
    prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(14)
    return s.getvalue()


def gl_breakdown(source, plan, repeats: int = 5) -> dict:
    """Seconds per 8-band pass of the pieces of render_lookup, timed standalone on cube 0's window:
    DN interleave (one strided copy per band into (lines, samples, 4)) and upload of the two
    RGBA16UI textures, and the read-back of the eight R32F targets straight into the output array
    (nothing pending: pure copy-out). The draw itself is what render_lookup's time leaves."""
    from archive.render.context import get_context, park_framebuffer

    ctx = get_context()
    job = plan.jobs[0]
    win, info = job.window, source.cubes[job.cube]
    dn = source.read_bands(job.cube, list(range(8)))
    out: dict = {}

    def timed(name, fn):
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            ctx.finish()
            ts.append(time.perf_counter() - t)
        out[name] = float(np.median(ts))

    block = np.empty((info.lines, info.samples, 4), np.uint16)

    def upload():
        for g in (0, 4):
            for c in range(4):
                block[..., c] = dn[g + c]
            ctx.texture((info.samples, info.lines), 4, block, dtype="u2", alignment=1).release()

    rbs = [ctx.renderbuffer((win.width, win.height), 1, dtype="f4") for _ in range(8)]
    fbo = ctx.framebuffer(color_attachments=rbs)
    fbo.use()
    fbo.clear(0.0, 0.0, 0.0, 0.0)
    vp = (0, 0, win.width, win.height)
    values = np.empty((8, win.height, win.width), np.float32)

    def read():
        for i in range(8):
            fbo.read_into(values, viewport=vp, components=1, attachment=i, dtype="f4",
                          write_offset=i * values[0].nbytes)

    timed("upload_dn_s", upload)
    timed("read_values_s", read)
    park_framebuffer()
    for o in (fbo, *rbs):
        o.release()
    out["window"] = [win.height, win.width]
    return out


# ---------------------------------------------------------------------------------------------
# 3. GDAL direct method
# ---------------------------------------------------------------------------------------------
def geolocation(source, cube: int, ground: float) -> tuple[np.ndarray, np.ndarray]:
    """UTM (X easting, Y northing), each (lines, samples) float64, for GDAL's geolocation arrays.

    GDAL's geolocation transformer takes the value at index (i, j) as the position of source pixel
    coordinate (j, i), i.e. the TOP-LEFT CORNER of pixel (line i, sample j) (checked: a 4 x 4
    affine test warps sample j onto x in [j, j + 1)). So we pass the corner of each pixel as the
    mesh defines it: sample j's left edge is the ray u = -t + 2t j / N (t = tan(fov / 2)), and line
    i's span starts half-way between the mid-exposure poses of lines i - 1 and i (the mesh centres
    line i's span on its mid-exposure row: L in [i - 0.5, i + 0.5)). The ray is intersected with
    the flat ground exactly, at every row (so the perspective spacing of samples on the ground is
    exact); the corner of line i is the mean of the ground points of rows i - 1 and i (the mesh
    interpolates linearly between rows too). Line 0's start comes from the previous cube's last
    line when it joins this one, else it is extrapolated from rows 0 and 1.
    """
    from scipy.spatial.transform import Rotation

    from archive.graph.plan import strip_links
    from archive.render.mesh import mid_exposure

    info = source.cubes[cube]
    poses = [source.poses(i) for i in range(len(source.cubes))]
    links = strip_links(source, poses)
    p = poses[cube]
    times, pos, att = [np.asarray(p.time, float)], [np.asarray(p.position, float)], [p.attitude]
    opening = cube > 0 and links[cube - 1]
    if opening:
        q = poses[cube - 1]
        times.insert(0, np.asarray(q.time, float)[-1:])
        pos.insert(0, np.asarray(q.position, float)[-1:])
        att.insert(0, q.attitude[-1:])
    if cube < len(links) and links[cube]:  # mid-exposure of the last line interpolates towards the next cube
        q = poses[cube + 1]
        times.append(np.asarray(q.time, float)[:1])
        pos.append(np.asarray(q.position, float)[:1])
        att.append(q.attitude[:1])
    mid_pos, mid_att = mid_exposure(np.concatenate(times), np.concatenate(pos), Rotation.concatenate(att),
                                    info.shutter_ms or 0.0)
    rows = slice(0, info.lines + (1 if opening else 0))
    mid_pos, mat = mid_pos[rows], mid_att.as_matrix()[rows]         # (r, 3), (r, 3, 3)
    n = info.samples
    t = np.tan(np.radians(FOV) / 2)
    u = -t + 2 * t * np.arange(n) / n                                # left edges
    d = mat[:, None, :, 1] * u[None, :, None] + mat[:, None, :, 2]   # (r, n, 3) NED ray directions
    d_ground = float(source.frame.origin_alt) - float(ground)
    lam = (d_ground - mid_pos[:, None, 2]) / d[..., 2]
    g = mid_pos[:, None, :2] + lam[..., None] * d[..., :2]           # (r, n, 2) N, E
    if opening:
        corner = 0.5 * (g[:-1] + g[1:])
    else:
        corner = np.empty_like(g)
        corner[1:] = 0.5 * (g[:-1] + g[1:])
        corner[0] = 1.5 * g[0] - 0.5 * g[1]
    x = corner[..., 1] + source.frame.origin_e
    y = corner[..., 0] + source.frame.origin_n
    return np.ascontiguousarray(x), np.ascontiguousarray(y)


def gdal_direct(source, plan, ground: float, work: Path, group: int, threads: int = 2,
                bands: int | None = None, write: bool = True) -> dict:
    from rasterio.warp import Resampling, reproject
    from tqdm import tqdm

    crs = plan.grid.crs
    per_cube = []
    with MemoryPoll() as poll:
        for job in plan.jobs:
            c, win = job.cube, job.window
            nb = bands or source.cubes[c].bands
            t0 = time.perf_counter()
            x, y = geolocation(source, c, ground)
            t_geo = time.perf_counter() - t0
            out = out_memmap(work / f"gdal_cube{c}.npy", (nb, win.height, win.width)) if write else None
            t_read = t_rad = t_warp = t_write = 0.0
            for b0 in tqdm(range(0, nb, group), desc=f"gdal cube {c}", unit="group", leave=False):
                idx = list(range(b0, min(b0 + group, nb)))
                t = time.perf_counter()
                dn = source.read_bands(c, idx)
                rad = source.radiometry(c, idx, MODE)
                t_read += time.perf_counter() - t
                t = time.perf_counter()
                src = (dn.astype(np.float32) - rad.dark[:, None, :]) * rad.gain[:, None, :]
                src /= rad.response[None, :, None]
                t_rad += time.perf_counter() - t
                t = time.perf_counter()
                dst = np.full((len(idx), win.height, win.width), np.nan, np.float32)
                reproject(src, dst, src_geoloc_array=(x, y), src_crs=crs, dst_transform=win.transform,
                          dst_crs=crs, resampling=Resampling.nearest, dst_nodata=np.nan,
                          num_threads=threads, warp_mem_limit=512)
                t_warp += time.perf_counter() - t
                t = time.perf_counter()
                if out is not None:
                    out[b0:b0 + len(idx)] = dst
                t_write += time.perf_counter() - t
            t = time.perf_counter()
            if out is not None:
                out.flush()
                del out
            t_write += time.perf_counter() - t
            wall = time.perf_counter() - t0
            per_cube.append({"cube": c, "bands": nb, "wall_s": wall, "geoloc_s": t_geo, "read_s": t_read,
                             "radiometry_s": t_rad, "warp_s": t_warp, "write_s": t_write,
                             "mpx_band_per_s": win.height * win.width * nb / 1e6 / wall})
    return {"per_cube": per_cube, "wall_s": sum(p["wall_s"] for p in per_cube), "group": group,
            "threads": threads, "peak_rss": poll.peak_rss, "peak_anon": poll.peak_anon}


def gdal_group_probe(source, plan, ground: float, work: Path, bands: int) -> dict:
    """Seconds per band of one reproject call on cube 0 for a few bands-per-call choices (one call each)."""
    import dataclasses

    one = dataclasses.replace(plan, jobs=plan.jobs[:1])
    out = {}
    for group in sorted({min(g, bands) for g in (4, 16, 64, bands)}):
        r = gdal_direct(source, one, ground, work, group, bands=group, write=False)
        pc = r["per_cube"][0]
        out[group] = {"call_s": pc["warp_s"], "s_per_band": (pc["wall_s"] - pc["geoloc_s"]) / group,
                      "peak_anon": r["peak_anon"]}
        print(f"  gdal probe: {group} bands/call: one call {pc['warp_s']:.2f} s, "
              f"{out[group]['s_per_band']:.3f} s/band, peak anon {fmt_gb(r['peak_anon'])} GB", flush=True)
    return out


# ---------------------------------------------------------------------------------------------
# Agreement of GDAL with ours
# ---------------------------------------------------------------------------------------------
def compare(plan, work: Path, step: int) -> dict:
    """Per-pixel agreement over every ``step``-th band of each cube window (ours vs GDAL)."""
    both = equal = close = ours_only = gdal_only = covered = 0
    for job in plan.jobs:
        a = np.load(work / f"core_cube{job.cube}.npy", mmap_mode="r")
        b = np.load(work / f"gdal_cube{job.cube}.npy", mmap_mode="r")
        for k in range(0, a.shape[0], step):
            x, y = np.asarray(a[k]), np.asarray(b[k])
            fx, fy = np.isfinite(x), np.isfinite(y)
            m = fx & fy
            covered += int(fx.sum())
            both += int(m.sum())
            ours_only += int((fx & ~fy).sum())
            gdal_only += int((fy & ~fx).sum())
            diff = np.abs(x[m] - y[m])
            scale = np.abs(x[m])
            equal += int((diff <= 1e-5 * scale + 1e-6).sum())
            close += int((diff <= 0.05 * scale + 1e-6).sum())
    return {"bands_step": step, "ours_covered": covered, "both": both,
            "equal_frac": equal / max(both, 1), "close5_frac": close / max(both, 1),
            "ours_not_gdal_frac": ours_only / max(covered, 1),
            "gdal_not_ours_frac": gdal_only / max(covered, 1)}


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------
def fmt_gb(b: float | None) -> str:
    return "-" if b is None else f"{b / 1e9:.2f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_flight_arguments(ap, bands=300, workdir="/tmp/archive-bench")
    ap.add_argument("--keep", action="store_true", help="keep the outputs (the simulated flight is always kept)")
    ap.add_argument("--gdal-group", type=int, default=0,
                    help="bands per reproject call (default: probe 4/16/64 on cube 0 and take the fastest)")
    ap.add_argument("--no-scaling", action="store_true", help="skip the end-to-end run on the first cube alone")
    ap.add_argument("--profile", action="store_true", help="also cProfile render_lookup on 32 bands of cube 0")
    ap.add_argument("--json", help="write all figures to this JSON file")
    args = ap.parse_args(argv)

    os.environ.setdefault("LP_NUM_THREADS", str(os.cpu_count() or 1))
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    runs = work / f"run_c{args.cubes}_b{args.bands}_s{args.samples}_l{args.lines}_g{args.gsd:g}"
    if runs.exists():
        shutil.rmtree(runs)
    runs.mkdir()
    R: dict = {"machine": machine(), "args": vars(args), "load": {}}
    R["load"]["start"] = load()
    flight = flight_dir(args)
    from archive.simulator.truth import load_truth

    ground = float(load_truth(flight).ground_height)
    R["warm_read_s"] = warm(flight)
    print(f"input warmed in the page cache ({R['warm_read_s']:.1f} s); load {load()}", flush=True)

    # Metadata-only plan (no GL): output size for the I/O floor.
    source, plan, mesh_s = make_plan(flight, args.gsd, ground)
    g = plan.grid
    out_bytes = g.width * g.height * plan.nbands * 4
    R["grid"] = {"width": g.width, "height": g.height, "bands": plan.nbands, "epsg": g.epsg, "gsd": g.gsd,
                 "mosaic_mb": out_bytes / MB,
                 "windows": [[j.window.height, j.window.width] for j in plan.jobs]}
    print(f"grid {g.width} x {g.height} px x {plan.nbands} bands ({out_bytes / MB:.0f} MB float32); "
          f"windows {R['grid']['windows']}", flush=True)

    print("[4] I/O floor", flush=True)
    R["floor"] = io_floor(flight, out_bytes, runs)
    R["load"]["floor"] = load()

    # Subprocesses first: no GL context may exist in this process when it forks.
    print("[1] end-to-end (archive render)", flush=True)
    R["e2e"] = end_to_end(flight, args, runs, ground)
    R["load"]["e2e"] = load()
    print(f"    {R['e2e']['wall_s']:.1f} s, peak tree RSS {fmt_gb(R['e2e']['peak_tree_rss'])} GB", flush=True)
    if args.cubes >= 2 and not args.no_scaling:
        one = one_cube_flight(flight, runs)
        R["e2e_1cube"] = end_to_end(one, args, runs, ground, tag="e2e_1cube")
        R["load"]["e2e_1cube"] = load()
        shutil.rmtree(Path(R["e2e_1cube"]["out"]), ignore_errors=True)

    print("[2] render core (in-process)", flush=True)
    R["core"] = render_core(source, plan, mesh_s, runs)
    R["load"]["core"] = load()
    from archive.render.context import gl_info

    R["gl"] = {k: v for k, v in gl_info().items() if k in ("renderer", "version", "max_texture_size")}
    R["gl_breakdown"] = gl_breakdown(source, plan)
    print("    per 8-band pass, standalone: " + ", ".join(
        f"{k} {v * 1000:.0f} ms" for k, v in R["gl_breakdown"].items() if k.endswith("_s")), flush=True)
    if args.profile:
        R["profile"] = profile_render(source, plan)
        print(R["profile"])

    print("[3] GDAL direct method", flush=True)
    group = args.gdal_group
    if not group:
        R["gdal_probe_s_per_band"] = gdal_group_probe(source, plan, ground, runs, plan.nbands)
        probe = R["gdal_probe_s_per_band"]
        group = min(probe, key=lambda k: probe[k]["s_per_band"])
    R["gdal"] = gdal_direct(source, plan, ground, runs, group)
    R["load"]["gdal"] = load()

    R["agreement"] = compare(plan, runs, step=max(1, plan.nbands // 30))
    report(R)
    if args.json:
        Path(args.json).write_text(json.dumps(R, indent=1, default=str))
    if not args.keep:
        shutil.rmtree(runs, ignore_errors=True)
    return 0


def report(R: dict) -> None:
    e, c, gd, f = R["e2e"], R["core"], R["gdal"], R["floor"]
    n = len(c["per_cube"])
    m = R["machine"]
    print()
    print(f"machine: {m['cpu']}, {m['cores']} cores, {m['ram_gb']} GB RAM; GL: {R['gl']['renderer']}")
    print(f"grid: {R['grid']['width']} x {R['grid']['height']} px x {R['grid']['bands']} bands at "
          f"{R['grid']['gsd']:g} m; {n} cube(s); warm page cache")
    print()
    print("| method | wall s | s / cube | Mpx·band/s | peak memory GB | output MB | split |")
    print("|---|---|---|---|---|---|---|")
    mpxb = R["grid"]["width"] * R["grid"]["height"] * R["grid"]["bands"] / 1e6
    print(f"| ours end-to-end (`archive.render` → Zarr) | {e['wall_s']:.1f} | {e['wall_s'] / n:.1f} | "
          f"{mpxb / e['wall_s']:.0f} (mosaic) | tree {fmt_gb(e['peak_tree_rss'])} (anon "
          f"{fmt_gb(e['peak_tree_anon'])}); largest proc {fmt_gb(e['largest_process_rss'])} | "
          f"{e['zarr_mb']:.0f} (zarr on disk) | incl. cluster start-up |")
    if "e2e_1cube" in R:
        e1 = R["e2e_1cube"]
        print(f"| ours end-to-end, first cube alone | {e1['wall_s']:.1f} | {e1['wall_s']:.1f} | - | tree "
              f"{fmt_gb(e1['peak_tree_rss'])} (anon {fmt_gb(e1['peak_tree_anon'])}); largest proc "
              f"{fmt_gb(e1['largest_process_rss'])} | {e1['zarr_mb']:.0f} | |")
    split = lambda p, keys: ", ".join(f"{k[:-2]} {p[k]:.1f}" for k in keys)  # noqa: E731
    for p in c["per_cube"]:
        print(f"| ours render core, cube {p['cube']} ({p['window'][0]} x {p['window'][1]} px) | {p['wall_s']:.1f} | "
              f"{p['wall_s']:.1f} | {p['mpx_band_per_s']:.0f} | proc {fmt_gb(c['peak_rss'])} (anon "
              f"{fmt_gb(c['peak_anon'])}) | {p['window'][0] * p['window'][1] * p['bands'] * 4 / MB:.0f} (.npy) | "
              f"{split(p, ['read_s', 'mesh_s', 'lookup_s', 'render_s', 'write_s'])} |")
    for p in gd["per_cube"]:
        print(f"| GDAL geoloc warp ({gd['group']} bands/call, {gd['threads']} threads), cube {p['cube']} | "
              f"{p['wall_s']:.1f} | {p['wall_s']:.1f} | {p['mpx_band_per_s']:.0f} | proc {fmt_gb(gd['peak_rss'])} "
              f"(anon {fmt_gb(gd['peak_anon'])}) | same | "
              f"{split(p, ['geoloc_s', 'read_s', 'radiometry_s', 'warp_s', 'write_s'])} |")
    print(f"| I/O floor (read .bil + write mosaic bytes, fsync) | {f['wall_s']:.1f} | {f['wall_s'] / n:.1f} | - | - | "
          f"{f['write_mb']:.0f} | read {f['read_s']:.1f} ({f['read_mb']:.0f} MB), write {f['write_s']:.1f} |")
    print()
    a = R["agreement"]
    print(f"GDAL / ours (render core): {gd['wall_s'] / c['wall_s']:.2f}x")
    print(f"GDAL / ours (end-to-end):  {gd['wall_s'] / e['wall_s']:.2f}x")
    print(f"ours end-to-end / I/O floor: {e['wall_s'] / f['wall_s']:.2f}x; render core / I/O floor: "
          f"{c['wall_s'] / f['wall_s']:.2f}x")
    print(f"peak memory per cube (end-to-end tree RSS / cubes): {fmt_gb(e['peak_tree_rss'] / n)} GB")
    print(f"agreement (every {a['bands_step']}th band): of pixels covered by both, {100 * a['equal_frac']:.2f} % equal, "
          f"{100 * a['close5_frac']:.2f} % within 5 %; covered by ours but NaN in GDAL: "
          f"{100 * a['ours_not_gdal_frac']:.3f} %; by GDAL but not ours: {100 * a['gdal_not_ours_frac']:.3f} %")
    p0 = c["per_cube"][0]
    passes = -(-p0["bands"] // 8)
    gb = R["gl_breakdown"]
    print(f"render core, cube 0, per 8-band pass: render_lookup {1000 * p0['render_s'] / passes:.0f} ms; standalone "
          + ", ".join(f"{k[:-2]} {1000 * v:.0f} ms" for k, v in gb.items() if k.endswith("_s")))
    if "gdal_probe_s_per_band" in R:
        print("GDAL probe (cube 0, one call each): " + "; ".join(
            f"{k} bands/call {v['call_s']:.1f} s ({v['s_per_band']:.3f} s/band, anon {fmt_gb(v['peak_anon'])} GB)"
            for k, v in R["gdal_probe_s_per_band"].items()))
    print("load average (1/5/15 min): " + "; ".join(f"{k} {v}" for k, v in R["load"].items()))


if __name__ == "__main__":
    raise SystemExit(main())
