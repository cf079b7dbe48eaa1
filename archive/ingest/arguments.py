"""``archive ingest``'s options of where and how it writes (``archive/cli.py`` adds them to the ingest
parser): ``--scheduler``, ``--cluster slurm`` and its ``--job-*`` options, ``--workers``, ``--threads``,
``--report``, ``--compression``, ``--checksum``; and :func:`where`, the place they name. Parsing only
(no Dask import)."""

from __future__ import annotations

import argparse

from archive.errors import InputError

__all__ = ["CHECKSUM_NAMES", "COMPRESSION_NAMES", "add_cluster_options", "where"]

#: ``--compression`` and ``--checksum`` choices, the default first.
COMPRESSION_NAMES = ("fast", "small")
CHECKSUM_NAMES = ("blake3", "sha256")

#: ``--cluster slurm``'s options (parser destinations) and the :class:`~archive.run.cluster.SlurmJobs` fields.
JOB_OPTIONS = {"ingest_jobs": "jobs", "job_queue": "queue", "job_cores": "cores", "job_memory": "memory",
               "job_walltime": "walltime"}


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text!r}")
    return value


def add_cluster_options(p: argparse.ArgumentParser) -> None:
    """Add the options of where an ingest runs and how it stores the DN to the ingest parser ``p``."""
    # the names of archive.collection.layout's DN_COMPRESSIONS and CHECKSUMS, not imported here (zarr: a slow
    # `archive --help`); tests/test_ingest_cluster.py checks that they are the same
    p.add_argument("--compression", choices=list(COMPRESSION_NAMES), default=COMPRESSION_NAMES[0],
                   help="the DN chunks' codec: fast (default: Blosc LZ4 9 + bit-shuffle, ~2 ms a 1000 x 900 chunk, "
                        "ratio ~1.8 on 12-bit DN) or small (Blosc Zstd 3 + bit-shuffle: ~8 %% fewer bytes for ~3x "
                        "the CPU); measured table: docs/ingest.md")
    p.add_argument("--checksum", choices=list(CHECKSUM_NAMES), default=CHECKSUM_NAMES[0],
                   help="checksum of every DN chunk and raw file: blake3 (default, ~3.5x faster) or sha256 (where a "
                        "policy asks for it); recorded with the store, which every reader and 'archive verify' follow")
    p.add_argument("--prewritten", metavar="DIR",
                   help="a folder of DN chunks 'archive watch' encoded as each cube closed: each that is exactly "
                        "what this ingest writes is moved in instead of written again (in this process only); the "
                        "collection is the same (docs/watch.md)")
    g = p.add_argument_group("where it runs (default: this process, every core; every flight checked before any is "
                             "written). On a cluster each flight is a unit of its own: checked and written by tasks "
                             "on the workers, published here; a flight that fails costs only itself (exit code 1)")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler address, e.g. tcp://host:8786: the workers see the raw folders (and any "
                        "--calibration, --dem, --navigation file) and the archive at the same paths; see docs/deploy.md")
    g.add_argument("--workers", type=_positive, metavar="N",
                   help="worker processes of a local Dask cluster (default 1: this process, no cluster)")
    g.add_argument("--threads", type=_positive, metavar="N",
                   help="threads writing chunks: of this process (default: every core), or of each local worker")
    g.add_argument("--report", metavar="FILE.json",
                   help="on a cluster: a JSON report of every flight (directory, id, status, error, seconds), "
                        "rewritten as each ends")
    g.add_argument("--cluster", choices=["slurm"], help="start the Dask workers as Slurm batch jobs "
                   "(dask-jobqueue's SLURMCluster; its scheduler runs in this command); see docs/deploy.md")
    j = p.add_argument_group("--cluster slurm: the worker jobs (an option left out: the 'jobqueue: slurm:' "
                             "configuration)")
    j.add_argument("--jobs", dest="ingest_jobs", type=_positive, metavar="N", help="worker jobs kept running (default 1)")
    j.add_argument("--job-queue", metavar="PARTITION", help="Slurm partition of the worker jobs")
    j.add_argument("--job-cores", type=_positive, metavar="N", help="CPUs per job: the worker's threads")
    j.add_argument("--job-memory", metavar="SIZE", help="memory per job, e.g. 16GB")
    j.add_argument("--job-walltime", metavar="HH:MM:SS", help="time limit of each worker job")


def where(args: argparse.Namespace):
    """Where the parsed ingest runs: a scheduler's address, a :class:`~archive.run.cluster.SlurmJobs`
    (``--cluster slurm``), or None (this process, or a local cluster of ``--workers`` N >= 2).
    InputError for options that contradict each other."""
    given = {f: getattr(args, d, None) for d, f in JOB_OPTIONS.items() if getattr(args, d, None) is not None}
    if getattr(args, "cluster", None) is None:
        if given:
            option = next(d for d, f in JOB_OPTIONS.items() if f in given)
            option = "--jobs" if option == "ingest_jobs" else "--" + option.replace("_", "-")
            raise InputError(option, "sizes the worker jobs of --cluster slurm", "add --cluster slurm")
        return getattr(args, "scheduler", None) or None
    if getattr(args, "scheduler", None):
        raise InputError("--cluster", "--cluster and --scheduler both say where the workers are", "give one of them")
    if args.workers is not None or args.threads is not None:
        raise InputError("--workers/--threads", "size a local cluster, not Slurm worker jobs",
                         "give --jobs and --job-cores instead")
    from archive.run.cluster import SlurmJobs

    return SlurmJobs(**given)
