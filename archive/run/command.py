"""``archive render``: the parsed options made into one :class:`~archive.run.options.RenderOptions`
(catalog queries resolved into collection ids) and written by :func:`archive.georectify`; prints a
summary. Batch jobs over the catalog too (one output per flight unless ``--mosaic``).
"""

from __future__ import annotations

import argparse
import math
import sys

from archive.errors import InputError

__all__ = ["render_keywords", "run"]


def query_ids(args: argparse.Namespace) -> list[str] | None:
    """Collection ids of ``--archive`` matching the ``--query-*`` filters (None when none is given);
    ``archive render`` and ``archive calibrate`` share these options."""
    bbox, when = args.query_bbox, args.query_datetime
    wavelength = args.query_wavelength
    if bbox is None and when is None and wavelength is None:
        return None
    if not args.archive:
        raise InputError("--query-*", "a catalog query needs the archive to search", "pass --archive ARCHIVE")
    if wavelength is not None and not (math.isfinite(wavelength) and wavelength > 0):
        raise InputError("--query-wavelength", f"{wavelength} is not a positive wavelength in nm")
    from archive.api import open_archive

    ids = open_archive(args.archive).search(bbox=bbox, datetime=when, wavelength=wavelength)
    if not ids:
        asked = ", ".join(f"{k} {v}" for k, v in (("--query-bbox", bbox), ("--query-datetime", when),
                                                   ("--query-wavelength", wavelength)) if v is not None)
        raise InputError(args.archive, f"no flight in the catalog matches {asked}",
                         "check the filters with 'archive catalog search'")
    return ids


#: Options of ``archive render`` that say how to run, not what to render.
RUN_KEYWORDS = ("quicklook", "scheduler", "workers", "threads", "overwrite", "quiet", "format", "resume")
#: ``--cluster slurm``'s options (parser destinations) and the :class:`~archive.run.cluster.SlurmJobs` fields they set.
JOB_OPTIONS = {"jobs": "jobs", "job_queue": "queue", "job_cores": "cores", "job_memory": "memory",
               "job_walltime": "walltime", "job_gpus": "gpus"}


def _where(args: argparse.Namespace):
    """Where to run: ``--scheduler``'s address, a :class:`~archive.run.cluster.SlurmJobs` for
    ``--cluster slurm``, or None (a local cluster)."""
    from archive.run.cluster import SlurmJobs

    given = {field: getattr(args, dest, None) for dest, field in JOB_OPTIONS.items()}
    given = {field: value for field, value in given.items() if value is not None}
    if getattr(args, "cluster", None) is None:
        if given:
            option = next(d for d, f in JOB_OPTIONS.items() if f in given).replace("_", "-")
            raise InputError(f"--{option}", "sizes the worker jobs of --cluster slurm", "add --cluster slurm")
        return args.scheduler
    if args.scheduler:
        raise InputError("--cluster", "--cluster and --scheduler both say where the workers are", "give one of them")
    if args.workers is not None or args.threads is not None:
        raise InputError("--workers/--threads", "size a local cluster, not Slurm worker jobs",
                         "give --jobs and --job-cores instead")
    return SlurmJobs(**given)


def render_keywords(args: argparse.Namespace, scheduler=None) -> dict:
    """The :func:`archive.georectify` keywords of parsed ``archive render`` options: every render
    option (:data:`archive.run.options.KEYWORDS`, the parser's destinations of the same names) and how
    to run; catalog queries resolved (matching ids added to the sources; one output per flight
    unless ``--mosaic``). ``scheduler``: where to run instead of the options' (a
    :class:`~archive.run.cluster.ClusterStart` already under way)."""
    from archive.run.options import KEYWORDS
    from archive.outputs.registry import format_named

    format_named(args.format)   # an unknown --format: one line, before anything is opened
    keywords = {"sources": list(args.sources or []), "out": args.out,
                **{name: getattr(args, name) for name in KEYWORDS + RUN_KEYWORDS},
                "scheduler": _where(args) if scheduler is None else scheduler}
    ids = query_ids(args)
    if ids is not None:
        keywords["sources"] += [i for i in ids if i not in keywords["sources"]]
        keywords["per_flight"] = not (args.mosaic or args.stack)
    if args.tiles is not None:
        if not args.archive:
            raise InputError("--tiles", "tiles the flights of an archive's catalog", "pass --archive A with "
                             "--query-bbox/--query-datetime/--query-wavelength (or collection ids)")
        if args.stack or args.mosaic:
            raise InputError("--tiles", f"--tiles and {'--stack' if args.stack else '--mosaic'} are two kinds of output",
                             "give one of them")
        keywords["tiles"] = args.tiles
        keywords["per_flight"] = False
    if args.stack:
        if ids is None and not keywords["sources"]:
            raise InputError("--stack", "stacks the flights of a catalog query or of SOURCE...",
                             "add --archive A with --query-bbox/--query-datetime/--query-wavelength")
        if args.mosaic:
            raise InputError("--stack", "--stack and --mosaic are two kinds of output", "give one of them")
        keywords["stack"] = True
        keywords.pop("format", None)
    return keywords


def run(args: argparse.Namespace) -> int:
    """``archive render``: :func:`archive.georectify` with the parsed options; prints a one-paragraph
    summary (batch mode: one line per flight as it finishes, done / skipped / failed with its reason,
    then the totals; exit code 1 when a flight failed)."""
    from archive.run.cluster import ClusterStart, SlurmJobs, phase

    phase("command")
    # The workers (or the connection to --scheduler) start now, while this process imports the
    # pipeline and opens and plans the inputs: those phases leave the other cores idle otherwise.
    # Slurm jobs are submitted where the command always did (after its checks of the options); a
    # --resume may find nothing to render: its workers start when needed.
    where = _where(args)
    if where is None and args.workers is None and small_job(args.sources or [], args):
        from archive.run.session import IN_PROCESS

        return _run(args, IN_PROCESS)   # no worker process to start
    starting = (None if isinstance(where, SlurmJobs) or args.resume
                else ClusterStart(where, args.workers, _say(args), args.threads))
    try:
        return _run(args, starting)
    finally:
        if starting is not None:
            starting.close()   # only one nobody took (the command failed before it needed workers)


#: Raw flights with at most this many bytes of DN in all render in this process (no worker process
#: spawned: a local cluster's start is 2.5-5 s of a tiny render; bench/bench_small.py). ``--workers
#: N`` asks for worker processes whatever the size.
SMALL_JOB_BYTES = 16 << 20


def small_job(sources: list, args: argparse.Namespace | None = None) -> bool:
    """Whether a render of ``sources`` is small enough to run in this process: only raw flight
    directories (a collection's or a catalog query's size is not read here), whose ``.bil`` files
    hold :data:`SMALL_JOB_BYTES` or fewer in all."""
    from pathlib import Path

    if not sources or (args is not None and any(getattr(args, k, None) is not None for k in
                                                ("query_bbox", "query_datetime", "query_wavelength"))):
        return False
    total = 0
    for source in sources:
        if not Path(source).is_dir():
            return False
        total += sum(p.stat().st_size for p in Path(source).glob("*.bil") if p.is_file())
        if total > SMALL_JOB_BYTES:
            return False
    return True


def _say(args: argparse.Namespace):
    """The progress-line ``say`` of :func:`archive.run.pipeline.progress_lines` (stderr through
    ``tqdm.write``; nothing with --quiet), without importing the pipeline."""
    def say(text: str) -> None:
        if not args.quiet:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stderr)

    return say


def _run(args: argparse.Namespace, starting) -> int:
    from archive.api import georectify
    from archive.run.cluster import phase
    from archive.run.pipeline import describe

    from tqdm import tqdm

    phase("imports")

    def tell(line: str) -> None:
        # past the progress bar (stderr, the same terminal): cleared, the line, the bar drawn again
        with tqdm.external_write_mode(file=sys.stdout):
            print(f"archive render: {line}", flush=True)

    s = georectify(**render_keywords(args, starting), tell=tell)
    phase("published")
    if "added" in s:
        n = len(s["flights"])
        print(f"archive render: stack {s['out']}: {n} flight{'s' if n != 1 else ''} on {s['width']} x {s['height']} px "
              f"at {s['gsd']:g} m, EPSG:{s['epsg']}, {s['bands']} band{'s' if s['bands'] != 1 else ''}: "
              f"{len(s['added'])} added, "
              f"{len(s['skipped'])} already there, {len(s['left_out'])} left out, in {s['seconds']:.1f} s.")
        return 0
    if "outputs" in s:
        n = len(s["outputs"])
        unit = "tile" if "tiles" in s else "flight"
        print(f"archive render: {n} {unit}{'s' if n != 1 else ''} in {s['seconds']:.1f} s: {s['done']} done, "
              f"{s['skipped']} skipped, {s['failed']} failed; report {s['report']}.")
        return 1 if s["failed"] else 0
    print(f"archive render: wrote {describe(s)} in {s['seconds']:.1f} s.")
    return 0

