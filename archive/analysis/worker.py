"""Worker preload of ``archive stats``' local clusters: imports ``dask.array`` (and with it xarray)
when the worker process starts, before :mod:`archive.run.cluster`'s own preload registers the
process's exit handler.

Why: the window tasks of :mod:`archive.analysis.zonal` slice the lazy stack with dask.array
functions, so a worker imports ``dask.array`` for its first task, and ``dask.array`` imports xarray,
which registers an ``atexit`` handler that must run once. Registered after the cluster's exit
handler (which runs the handlers registered before it itself), it ran twice at the worker's exit
and printed a traceback (``CachingFileManager has no attribute '__del__'``). Imported here, first,
it is registered before that handler and runs once.
"""

from __future__ import annotations

import dask.array  # noqa: F401  (the point of this module)

__all__: list[str] = []
