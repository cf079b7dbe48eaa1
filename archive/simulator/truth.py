"""Ground truth of a simulated flight: scene, continuous trajectory, per-line poses and footprint.

On disk, ``<flight>/truth/truth.json`` holds the parameters (site, zone, scene shapes and texture,
trajectory and wobble terms, per-cube exposure) and ``truth.npz`` the arrays (wavelengths, spectra,
per-cube line times, positions and attitude quaternions). :func:`load_truth` rebuilds the same
objects, so every test evaluates the same functions the simulator used.

Coordinates: UTM metres (E, N) of ``epsg``, altitude m above the WGS-84 ellipsoid; times are GPS
seconds on the ``.lcf`` scale; attitude is camera (= body) -> NED with N = grid north.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from archive.errors import FormatError, MissingInputError
from archive.simulator.scene import Scene, points_in_polygon
from archive.simulator.sensor import ground_points
from archive.simulator.trajectory import Trajectory, convergence

__all__ = ["CubeTruth", "Truth", "load_truth", "save_truth", "TRUTH_VERSION"]

TRUTH_VERSION = 1


@dataclass(frozen=True, eq=False)
class CubeTruth:
    """One cube: ``line_time`` (lines,) GPS s at exposure start; ``position_utm`` (lines, 3) E, N,
    alt (m) of the camera then; ``attitude`` (lines,) camera -> NED (grid north); exposure
    ``shutter_ms`` (ms) and ``gain_db`` (dB); ``framerate`` (Hz)."""

    base: str
    line_time: np.ndarray
    position_utm: np.ndarray
    attitude: Rotation
    shutter_ms: float
    gain_db: float
    framerate: float

    @property
    def lines(self) -> int:
        return int(self.line_time.size)


@dataclass(frozen=True, eq=False)
class Truth:
    """Everything the simulator knows. ``wavelengths`` (bands,) nm; ``cubes`` in capture order;
    ``samples`` per line; ``site`` (lon, lat) degrees; ``scene`` and ``flight`` evaluate the
    radiance and the continuous motion."""

    directory: Path
    epsg: int
    fov_deg: float
    ground_height: float
    wavelengths: np.ndarray
    cubes: tuple[CubeTruth, ...]
    samples: int
    site: tuple[float, float]
    seed: int
    scene: Scene
    flight: Trajectory

    # --- scene ------------------------------------------------------------------------------------
    def radiance(self, e, n) -> np.ndarray:
        """True radiance (bands, *e.shape) at UTM points (m), point value (no blur)."""
        return self.scene.radiance(e, n)

    def radiance_box(self, e, n, size: float, supersample: int = 8) -> np.ndarray:
        """True radiance (bands, *e.shape) averaged over size x size m squares centred at (e, n)
        (supersample x supersample points per square)."""
        return self.scene.radiance_box(e, n, size, supersample)

    def abundance(self, e, n) -> np.ndarray:
        """Material abundances (materials, *e.shape) at UTM points; see ``scene.materials``."""
        return self.scene.abundance(e, n)

    @property
    def spectra(self) -> np.ndarray:
        """(materials, bands) radiance spectra: radiance = spectra.T @ abundance."""
        return self.scene.spectra

    def homogeneous_patches(self) -> list[dict]:
        """Homogeneous patches (name, material, material_name, bounds, interior (W, S, E, N) m)."""
        return self.scene.homogeneous_patches()

    # --- motion -------------------------------------------------------------------------------------
    def trajectory(self, t) -> tuple[np.ndarray, Rotation]:
        """Continuous truth at lcf-scale GPS times ``t`` (n,): positions (n, 3) E, N, alt (m) and
        attitudes (n,) body (= camera) -> NED (grid north)."""
        return self.flight(t)

    @property
    def convergence(self) -> float:
        """Grid bearing of true north at the site (rad; add to a true heading for a grid one)."""
        return float(convergence(self.site[0], self.site[1], self.epsg))

    @property
    def nominal_gsd(self) -> float:
        """Across-track sample spacing at nadir at the mean height above ground (m)."""
        height = float(np.mean(np.concatenate([c.position_utm[:, 2] for c in self.cubes]))) - self.ground_height
        return 2.0 * height * math.tan(math.radians(self.fov_deg) / 2.0) / self.samples

    @property
    def strips(self) -> list[tuple[int, ...]]:
        """Cube indices of each strip: consecutive cubes whose first line follows the previous
        cube's last line within 1.5 frame intervals (no turn between them)."""
        out: list[list[int]] = []
        for k, cube in enumerate(self.cubes):
            if out:
                prev = self.cubes[out[-1][-1]]
                if cube.line_time[0] - prev.line_time[-1] <= 1.5 / prev.framerate:
                    out[-1].append(k)
                    continue
            out.append([k])
        return [tuple(s) for s in out]

    # --- footprint ---------------------------------------------------------------------------------
    @cached_property
    def _footprints(self) -> list[np.ndarray]:
        t_half = math.tan(math.radians(self.fov_deg) / 2.0)
        edges = np.array([-t_half, t_half])
        polygons = []
        for strip in self.strips:
            t = np.concatenate([self.cubes[k].line_time + self.cubes[k].shutter_ms / 2000.0 for k in strip])
            e, n = ground_points(self.flight, t, edges)
            left = np.stack([e[:, 0], n[:, 0]], axis=1)
            right = np.stack([e[:, 1], n[:, 1]], axis=1)
            polygons.append(np.concatenate([left, right[::-1]]))
        return polygons

    def footprint(self) -> list[np.ndarray]:
        """One polygon per strip, (k, 2) UTM (E, N) vertices (not repeated at the end): the left
        swath edge from the first to the last line, then the right edge back, each line's edge
        taken at its mid-exposure pose."""
        return [p.copy() for p in self._footprints]

    def covered(self, e, n) -> np.ndarray:
        """True where UTM points (m) lie inside the true footprint (union of strips); shape of e."""
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        shape = e.shape
        e, n = e.ravel(), n.ravel()
        inside = np.zeros(e.size, bool)
        for poly in self._footprints:
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            idx = np.nonzero((e >= lo[0]) & (e <= hi[0]) & (n >= lo[1]) & (n <= hi[1]))[0]
            inside[idx[points_in_polygon(poly, e[idx], n[idx])]] = True
        return inside.reshape(shape)


# --- persistence -----------------------------------------------------------------------------------
def save_truth(truth: Truth, folder: str | os.PathLike) -> None:
    """Write ``truth.json`` and ``truth.npz`` into ``folder`` (created)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta = {
        "version": TRUTH_VERSION, "epsg": truth.epsg, "fov_deg": truth.fov_deg,
        "ground_height": truth.ground_height, "samples": truth.samples, "site": list(truth.site),
        "seed": truth.seed, "scene": truth.scene.to_dict(), "trajectory": truth.flight.to_dict(),
        "cubes": [{"base": c.base, "shutter_ms": c.shutter_ms, "gain_db": c.gain_db,
                   "framerate": c.framerate, "lines": c.lines} for c in truth.cubes],
        "notes": ("UTM metres of epsg, altitude above the WGS-84 ellipsoid, GPS seconds (lcf scale); "
                  "attitude quaternions (x, y, z, w) camera -> NED with N = grid north; "
                  "radiance = spectra.T @ abundance"),
    }
    arrays = {"wavelengths": truth.wavelengths, "spectra": truth.scene.spectra}
    for k, c in enumerate(truth.cubes):
        arrays[f"line_time_{k}"] = c.line_time
        arrays[f"position_utm_{k}"] = c.position_utm
        arrays[f"attitude_quat_{k}"] = c.attitude.as_quat()
    for k, poly in enumerate(truth.footprint()):
        arrays[f"footprint_{k}"] = poly
    np.savez(folder / "truth.npz", **arrays)
    (folder / "truth.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")


def load_truth(directory: str | os.PathLike) -> Truth:
    """Read the truth of a simulated flight: ``directory`` is the flight directory (holding
    ``truth/``) or the ``truth`` folder itself."""
    directory = Path(directory)
    folder = directory / "truth" if (directory / "truth" / "truth.json").exists() else directory
    flight_dir = folder.parent if folder.name == "truth" else folder
    json_path, npz_path = folder / "truth.json", folder / "truth.npz"
    for path in (json_path, npz_path):
        if not path.exists():
            raise MissingInputError(path, "simulator truth",
                                    "point at a directory written by 'archive simulate'")
    meta = json.loads(json_path.read_text(encoding="utf-8"))
    if meta.get("version") != TRUTH_VERSION:
        raise FormatError(json_path, f"truth version {meta.get('version')!r}, expected {TRUTH_VERSION}",
                          "re-run 'archive simulate'")
    with np.load(npz_path) as z:
        arrays = {k: z[k] for k in z.files}
    cubes = tuple(
        CubeTruth(c["base"], arrays[f"line_time_{k}"], arrays[f"position_utm_{k}"],
                  Rotation.from_quat(arrays[f"attitude_quat_{k}"]), float(c["shutter_ms"]),
                  float(c["gain_db"]), float(c["framerate"]))
        for k, c in enumerate(meta["cubes"]))
    scene = Scene.from_dict(meta["scene"], arrays["wavelengths"], arrays["spectra"])
    return Truth(flight_dir, int(meta["epsg"]), float(meta["fov_deg"]), float(meta["ground_height"]),
                 arrays["wavelengths"], cubes, int(meta["samples"]), tuple(meta["site"]),
                 int(meta["seed"]), scene, Trajectory.from_dict(meta["trajectory"]))
