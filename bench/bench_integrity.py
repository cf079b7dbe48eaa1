"""What checking every DN chunk against its recorded sha256 costs a render (issue 19).

Simulates and ingests one flight, then renders it from the collection in this process
(``archive.mosaic(...).compute()``, the render graph's task bodies, GL on llvmpipe) alternately with
the checked reads (what every render does) and with the same chunks read unchecked
(``CheckedDn.read`` swapped for a plain read of the same chunks), ``--repeat`` times each; also the
sha256 time alone over every chunk the render reads. Prints the medians and the overhead.

    .venv/bin/python bench/bench_integrity.py                                 # 4 cubes x 500 x 256 x 32
    .venv/bin/python bench/bench_integrity.py --cubes 2 --lines 1000 --samples 900 --bands 60
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (the flight options)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    br.add_flight_arguments(ap, bands=32, workdir="/tmp/bench_integrity", cubes=4, samples=256, lines=500, gsd=0.05)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import archive
    from archive.collection import CheckedDn, chunk_digest
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    work = Path(args.workdir)
    shutil.rmtree(work, ignore_errors=True)
    simulate_flight(work / "flight", cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines)
    (r,) = ingest([str(work / "flight")], work / "archive", 47.5, progress=False)
    store = work / "archive" / "collections" / f"{r.cid}.zarr"

    checked = CheckedDn.read

    def unchecked(self, band, line0, line1):
        total, c = int(self.array.shape[1]), self.chunk
        out = np.empty((line1 - line0, int(self.array.shape[2])), self.dtype)
        for k in range(line0 // c, -(-line1 // c)):
            a, b = k * c, min((k + 1) * c, total)
            values = self.array[band, a:b]
            lo, hi = max(a, line0), min(b, line1)
            out[lo - line0:hi - line0] = values[lo - a:hi - a]
        return out

    def render() -> float:
        ds = archive.mosaic(r.cid, archive=work / "archive", gsd=args.gsd)
        t = time.perf_counter()
        ds.radiance.compute(scheduler="threads")
        return time.perf_counter() - t

    render()  # warm: page cache, GL context, shader compilation
    times = {"checked": [], "unchecked": []}
    for _ in range(args.repeat):
        for name, read in (("checked", checked), ("unchecked", unchecked)):
            CheckedDn.read = read
            times[name].append(render())
    CheckedDn.read = checked
    dn = CheckedDn(store)
    nbands, total = dn.array.shape[0], dn.array.shape[1]
    t = time.perf_counter()
    for b in range(nbands):
        for a in range(0, total, dn.chunk):
            chunk_digest(dn.array[b, a:a + dn.chunk])
    read_and_hash = time.perf_counter() - t
    t = time.perf_counter()
    for b in range(nbands):
        for a in range(0, total, dn.chunk):
            dn.array[b, a:a + dn.chunk]
    read_only = time.perf_counter() - t
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"flight {args.cubes} cubes x {args.lines} lines x {args.samples} samples x {args.bands} bands "
          f"({nbands * total * dn.array.shape[2] * 2 / 1e6:.0f} MB of DN), gsd {args.gsd} m, load "
          f"{os.getloadavg()[0]:.2f}")
    print(f"render checked   median {med['checked']:.3f} s  {['%.3f' % v for v in times['checked']]}")
    print(f"render unchecked median {med['unchecked']:.3f} s  {['%.3f' % v for v in times['unchecked']]}")
    print(f"overhead {100 * (med['checked'] - med['unchecked']) / med['unchecked']:+.1f} % of the render; "
          f"sha256 of every chunk alone {read_and_hash - read_only:.3f} s "
          f"({100 * (read_and_hash - read_only) / med['checked']:.1f} % of the checked render)")


if __name__ == "__main__":
    main()
