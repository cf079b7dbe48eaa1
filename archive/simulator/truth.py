"""Ground truth of a simulated flight: scene, continuous trajectory, per-line poses and footprint.

On disk, ``<flight>/truth/truth.json`` holds the parameters (site, zone, scene shapes and texture,
trajectory and wobble terms, per-cube exposure) and ``truth.npz`` the arrays (wavelengths, spectra,
per-cube line times, positions and attitude quaternions). :func:`load_truth` rebuilds the same
objects, so every test evaluates the same functions the simulator used.

Coordinates: UTM metres (E, N) of ``epsg`` (the zone of the site, also for points beyond a zone
border), altitude m above the WGS-84 ellipsoid; the evaluation functions also take points in another
CRS (``crs=``: an EPSG code such as the neighbouring UTM zone's, or 4326 for lon/lat). Times are TRUE
GPS seconds of exposure start: the ``.lcf`` scale plus the camera's ``sync_offset`` (see
:class:`Truth`); per-line poses are the CAMERA's (``boresight_deg`` / ``lever_arm_m`` applied), while the
``.lcf`` records the INS (:meth:`Truth.ins_trajectory`).

Options added after version 1 (sync offset, mounting, dropped frames, pause, banked turns recorded) are
written only when set, so a default flight's truth is unchanged and older truths load with defaults.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer
from scipy.spatial.transform import Rotation

from archive.errors import FormatError, MissingInputError
from archive.simulator.mount import Mount, camera_path
from archive.simulator.scene import Scene, points_in_polygon
from archive.simulator.sensor import ground_points
from archive.simulator.terrain import Terrain
from archive.simulator.trajectory import Trajectory, convergence

__all__ = ["CubeTruth", "Truth", "load_truth", "save_truth", "TRUTH_VERSION",
           "FOOTPRINT_MAX_OFF_NADIR_DEG"]

TRUTH_VERSION = 1
#: lines whose swath edge is seen further off nadir than this (banked turns) are left out of the footprint
FOOTPRINT_MAX_OFF_NADIR_DEG = 75.0


@lru_cache(maxsize=16)
def _transformer(source: str, target: int) -> Transformer:
    return Transformer.from_crs(CRS.from_user_input(source), CRS.from_epsg(target), always_xy=True)


def _crs_key(crs) -> str:
    """A hashable description of ``crs`` (EPSG int, 'EPSG:x' string, pyproj CRS, ...)."""
    if isinstance(crs, (int, np.integer)):
        return f"EPSG:{int(crs)}"
    if isinstance(crs, CRS):
        return crs.to_wkt()
    return str(crs)


@dataclass(frozen=True, eq=False)
class CubeTruth:
    """One cube: ``line_time`` (lines,) true GPS s at exposure start; ``position_utm`` (lines, 3) E,
    N, alt (m) of the camera then (lever arm applied); ``attitude`` (lines,) camera -> NED (grid
    north, boresight applied); exposure ``shutter_ms`` (ms) and ``gain_db`` (dB); ``framerate`` (Hz)."""

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
    radiance and the continuous motion of the platform (INS).

    Recorder realism (defaults = an ideal recorder): ``sync_offset`` (s) the true camera-to-navigation
    offset: a line's true time = lcf_t0 + (times[i] - times[0]) + sync_offset; ``mount`` the true
    camera mounting (``boresight_deg`` (roll, pitch, yaw) deg, ``lever_arm_m`` (x, y, z) m, body frame);
    ``dropped_frames`` frames dropped at each cube switch within a pass; ``pause_cube`` /
    ``pause_line`` / ``pause_s``: the recorder stopped ``pause_s`` s before line ``pause_line`` of cube
    ``pause_cube`` (None / None / 0: no pause); ``record_turns``: the end of each pass's recording is
    flown in the turn (``bank_deg``: the sustained bank of the turns, 0 for flat half circles).
    ``gnss_bias_m``: (dE, dN, dU) metres the recorded ``.lcf`` positions are off the truth (recorded =
    true + bias: the GNSS error of a kit without RTK); the correction ``archive calibrate --reference``
    estimates against an unbiased reference is its negative. ``ground_changes``: the fraction of
    the ground painted with new material patches after the scene was drawn (a field that changed
    since an earlier flight). ``terrain``: the analytic height field the rays were traced to (None: flat ground at
    ``ground_height``); the footprint then follows it and :meth:`visible` says which ground a line sees."""

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
    sync_offset: float = 0.0
    mount: Mount = field(default_factory=Mount)
    dropped_frames: int = 0
    pause_cube: int | None = None
    pause_line: int | None = None
    pause_s: float = 0.0
    record_turns: bool = False
    terrain: Terrain | None = None
    gnss_bias_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ground_changes: float = 0.0

    # --- recorder options -----------------------------------------------------------------------
    @property
    def boresight_deg(self) -> tuple[float, float, float]:
        return tuple(self.mount.boresight_deg)

    @property
    def lever_arm_m(self) -> tuple[float, float, float]:
        return tuple(self.mount.lever_arm_m)

    @property
    def bank_deg(self) -> float:
        """Sustained bank of the turns between passes (deg), 0 for the flat half-circle turns."""
        return float(self.flight.bank_deg)

    @property
    def crs(self) -> str:
        """'EPSG:<epsg>': the CRS of every UTM coordinate of the truth."""
        return f"EPSG:{self.epsg}"

    def in_turn(self, cube: int) -> np.ndarray:
        """(lines,) True for the lines of cube ``cube`` flown in a turn between passes."""
        return self.flight.turning(self.cubes[cube].line_time)

    # --- coordinates ------------------------------------------------------------------------------
    def to_utm(self, x, y, crs=None) -> tuple[np.ndarray, np.ndarray]:
        """Points (x, y) in ``crs`` (EPSG code, 'EPSG:x', pyproj CRS; 4326: lon, lat degrees; None:
        the truth's own UTM) -> UTM E, N (m) of the truth's ``epsg``."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        if crs is None or _crs_key(crs) == self.crs:
            return x, y
        e, n = _transformer(_crs_key(crs), self.epsg).transform(x, y)
        return np.asarray(e, float).reshape(x.shape), np.asarray(n, float).reshape(x.shape)

    def from_utm(self, e, n, crs=None) -> tuple[np.ndarray, np.ndarray]:
        """UTM E, N (m) of the truth's ``epsg`` -> (x, y) in ``crs`` (see :meth:`to_utm`)."""
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        if crs is None or _crs_key(crs) == self.crs:
            return e, n
        inverse = Transformer.from_crs(CRS.from_epsg(self.epsg), CRS.from_user_input(_crs_key(crs)),
                                       always_xy=True)
        x, y = inverse.transform(e, n)
        return np.asarray(x, float).reshape(e.shape), np.asarray(y, float).reshape(e.shape)

    # --- scene ------------------------------------------------------------------------------------
    def radiance(self, e, n, crs=None) -> np.ndarray:
        """True radiance (bands, *e.shape) at UTM points (m), point value (no blur); points in
        another CRS with ``crs`` (see :meth:`to_utm`)."""
        return self.scene.radiance(*self.to_utm(e, n, crs))

    def radiance_box(self, e, n, size: float, supersample: int = 8, crs=None) -> np.ndarray:
        """True radiance (bands, *e.shape) averaged over size x size squares centred at (e, n)
        (supersample x supersample points per square). With ``crs``, the squares are squares of that
        CRS (its axes, ``size`` in its units, e.g. a pixel of a render made in the other UTM zone)."""
        if crs is None or _crs_key(crs) == self.crs:
            return self.scene.radiance_box(e, n, size, supersample)
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        offsets = ((np.arange(supersample) + 0.5) / supersample - 0.5) * float(size)
        oe, on = (g.ravel() for g in np.meshgrid(offsets, offsets))
        flat_e, flat_n = e.ravel(), n.ravel()
        materials = len(self.scene.materials)
        out = np.zeros((materials, flat_e.size))
        step = max(1, (1 << 18) // oe.size)
        for s0 in range(0, flat_e.size, step):
            pe, pn = self.to_utm(flat_e[s0:s0 + step, None] + oe[None, :],
                                 flat_n[s0:s0 + step, None] + on[None, :], crs)
            a = self.scene.abundance(pe.ravel(), pn.ravel())
            out[:, s0:s0 + step] = a.reshape(materials, -1, oe.size).mean(axis=2)
        return np.tensordot(self.scene.spectra.T, out.reshape((materials,) + e.shape), axes=(1, 0))

    def abundance(self, e, n, crs=None) -> np.ndarray:
        """Material abundances (materials, *e.shape) at UTM points; see ``scene.materials``."""
        return self.scene.abundance(*self.to_utm(e, n, crs))

    @property
    def spectra(self) -> np.ndarray:
        """(materials, bands) radiance spectra: radiance = spectra.T @ abundance."""
        return self.scene.spectra

    def homogeneous_patches(self) -> list[dict]:
        """Homogeneous patches (name, material, material_name, bounds, interior (W, S, E, N) m)."""
        return self.scene.homogeneous_patches()

    # --- motion -------------------------------------------------------------------------------------
    @property
    def camera(self):
        """The camera path (``position(t)``, ``attitude(t)``): ``flight`` seen through ``mount``."""
        return camera_path(self.flight, self.mount)

    def trajectory(self, t) -> tuple[np.ndarray, Rotation]:
        """Continuous truth of the CAMERA at true GPS times ``t`` (n,): positions (n, 3) E, N, alt (m)
        and attitudes (n,) camera -> NED (grid north). Equal to :meth:`ins_trajectory` unless the
        flight has a boresight or a lever arm."""
        return self.camera(t)

    def ins_trajectory(self, t) -> tuple[np.ndarray, Rotation]:
        """Continuous truth of the INS / body (what the ``.lcf`` records) at GPS times ``t`` (n,):
        positions (n, 3) E, N, alt (m) and attitudes (n,) body -> NED (grid north)."""
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
        cube's last line within 1.5 frame intervals plus the dropped frames (a recorder's cube
        switch, no turn between them). A pause inside a cube splits the footprint, not the strip."""
        out: list[list[int]] = []
        for k, cube in enumerate(self.cubes):
            if out:
                prev = self.cubes[out[-1][-1]]
                if cube.line_time[0] - prev.line_time[-1] <= (1.5 + self.dropped_frames) / prev.framerate:
                    out[-1].append(k)
                    continue
            out.append([k])
        return [tuple(s) for s in out]

    # --- footprint ---------------------------------------------------------------------------------
    @cached_property
    def _footprints(self) -> list[np.ndarray]:
        return [poly for _, _, poly in self._footprint_parts]

    @cached_property
    def _footprint_parts(self) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(strip index, mid-exposure times of the part's lines, polygon) of every footprint part."""
        t_half = math.tan(math.radians(self.fov_deg) / 2.0)
        edges = np.array([-t_half, t_half])
        camera = self.camera
        cos_limit = math.cos(math.radians(FOOTPRINT_MAX_OFF_NADIR_DEG))
        polygons = []
        for s_index, strip in enumerate(self.strips):
            t = np.concatenate([self.cubes[k].line_time + self.cubes[k].shutter_ms / 2000.0 for k in strip])
            e, n = ground_points(camera, t, edges, self.terrain)
            # split at a pause and leave out lines seen too far off nadir (banked turns)
            starts = np.cumsum([0] + [self.cubes[k].lines for k in strip])
            cut = np.zeros(t.size, bool)
            if self.pause_cube in strip:
                cut[starts[strip.index(self.pause_cube)] + self.pause_line] = True
            m = camera.attitude(t).as_matrix()
            ok = np.ones(t.size, bool)
            for u in edges:
                d = m[:, :, 1] * u + m[:, :, 2]
                ok &= d[:, 2] >= cos_limit * np.linalg.norm(d, axis=1)
            ok &= np.isfinite(e).all(axis=1)
            run = np.cumsum(cut | np.concatenate([[False], ok[1:] != ok[:-1]]))
            for r in np.unique(run[ok]):
                sel = ok & (run == r)
                if sel.sum() < 2:
                    continue
                left = np.stack([e[sel, 0], n[sel, 0]], axis=1)
                right = np.stack([e[sel, 1], n[sel, 1]], axis=1)
                ring = [left, right[::-1]]
                if self.terrain is not None:   # the first and last lines' traces curve over the terrain
                    inner = np.linspace(-t_half, t_half, 129)[1:-1]
                    ends = t[sel][[0, -1]]
                    te, tn = ground_points(camera, ends, inner, self.terrain)
                    ring = [left, np.stack([te[1], tn[1]], axis=1), right[::-1],
                            np.stack([te[0], tn[0]], axis=1)[::-1]]
                polygons.append((s_index, t[sel], np.concatenate(ring)))
        return polygons

    def footprint(self, crs=None) -> list[np.ndarray]:
        """One polygon per strip, (k, 2) UTM (E, N) vertices (not repeated at the end): the left
        swath edge from the first to the last line, then the right edge back, each line's edge
        taken at its mid-exposure pose. A pause splits a strip's polygon in two; lines whose swath
        edge is seen more than FOOTPRINT_MAX_OFF_NADIR_DEG off nadir (steep banks) are left out.
        ``crs``: vertices in that CRS instead (see :meth:`to_utm`)."""
        if crs is not None and _crs_key(crs) != self.crs:
            return [np.stack(self.from_utm(p[:, 0], p[:, 1], crs), axis=1) for p in self._footprints]
        return [p.copy() for p in self._footprints]

    def covered(self, e, n, crs=None) -> np.ndarray:
        """True where UTM points (m) lie inside the true footprint (union of strips); shape of e.
        ``crs``: points in that CRS instead (see :meth:`to_utm`)."""
        e, n = self.to_utm(e, n, crs)
        shape = e.shape
        e, n = e.ravel(), n.ravel()
        inside = np.zeros(e.size, bool)
        for poly in self._footprints:
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            idx = np.nonzero((e >= lo[0]) & (e <= hi[0]) & (n >= lo[1]) & (n <= hi[1]))[0]
            inside[idx[points_in_polygon(poly, e[idx], n[idx])]] = True
        return inside.reshape(shape)

    def ground_height_at(self, e, n, crs=None) -> np.ndarray:
        """Height of the ground (m above the ellipsoid) at UTM points: the terrain's, else the flat
        ``ground_height``; shape of e."""
        e, n = self.to_utm(e, n, crs)
        if self.terrain is None:
            return np.full(e.shape, float(self.ground_height))
        return self.terrain.height(e, n)

    def visible(self, e, n, crs=None) -> np.ndarray:
        """True where the ground at UTM points (m) is seen by a line: inside the footprint of a part
        of a strip, and the ray from the camera (when that part's field of view sweeps the point,
        the mid-exposure pose interpolated between the two lines it falls between) meets the terrain
        first there (within 1 cm). Equal to :meth:`covered` on flat ground. Shape of e; ``crs``:
        points in that CRS instead (see :meth:`to_utm`)."""
        e, n = self.to_utm(e, n, crs)
        shape = e.shape
        e, n = e.ravel(), n.ravel()
        if self.terrain is None:
            return self.covered(e, n).reshape(shape)
        t_half = math.tan(math.radians(self.fov_deg) / 2.0)
        seen = np.zeros(e.size, bool)
        camera = self.camera
        for _, t, poly in self._footprint_parts:
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            idx = np.nonzero((e >= lo[0]) & (e <= hi[0]) & (n >= lo[1]) & (n <= hi[1]) & ~seen)[0]
            idx = idx[points_in_polygon(poly, e[idx], n[idx])]
            if idx.size == 0:
                continue
            pe, pn = e[idx], n[idx]
            ph = self.terrain.height(pe, pn)
            pos, att = camera(t)
            xaxis = att.as_matrix()[:, :, 0]                       # camera x in N, E, D
            points = np.stack([pn, pe, ph], axis=1)
            a = np.zeros(idx.size, np.intp)
            b = np.full(idx.size, t.size - 1, np.intp)
            fa, fb = _along(points, pos[a], xaxis[a]), _along(points, pos[b], xaxis[b])
            ok = np.sign(fa) != np.sign(fb)
            for _ in range(int(np.ceil(np.log2(max(t.size, 2)))) + 1):
                m = (a + b) // 2
                fm = _along(points, pos[m], xaxis[m])
                same = np.sign(fm) == np.sign(fa)
                a = np.where(same, m, a)
                fa = np.where(same, fm, fa)
                b = np.where(same, b, m)
                fb = np.where(same, fb, fm)
            ts = t[a] + (t[b] - t[a]) * fa / np.where(fa != fb, fa - fb, 1.0)
            cpos, catt = camera(ts)
            v = np.stack([pn - cpos[:, 1], pe - cpos[:, 0], cpos[:, 2] - ph], axis=1)   # N, E, D
            cam = catt.inv().apply(v)
            ok &= (cam[:, 2] > 0) & (np.abs(cam[:, 1]) <= t_half * cam[:, 2] * (1 + 1e-9))
            lam = self.terrain.intersect(cpos, v)
            ok &= np.isfinite(lam) & (lam >= 1.0 - 0.01 / np.linalg.norm(v, axis=1))
            seen[idx[ok]] = True
        return seen.reshape(shape)


def _along(points: np.ndarray, position: np.ndarray, xaxis: np.ndarray) -> np.ndarray:
    """Camera-x coordinates (m) of ground points (n, 3: N, E, altitude) seen from cameras at
    ``position`` (n, 3: E, N, altitude) whose x axes (N, E, D) are ``xaxis`` (n, 3): the sign says on
    which side of each camera's line of view a point lies."""
    v = np.stack([points[:, 0] - position[:, 1], points[:, 1] - position[:, 0], position[:, 2] - points[:, 2]],
                 axis=1)
    return np.einsum("ij,ij->i", v, xaxis)


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
    # recorder options added after version 1: only when set (a default truth stays as it was)
    if truth.sync_offset:
        meta["sync_offset"] = truth.sync_offset
        meta["notes_sync_offset"] = ("line times and poses are TRUE: a line's true time is lcf_t0 + "
                                     "(times[i] - times[0]) + sync_offset; each .lcf starts at its cube's "
                                     "first true line time - sync_offset")
    if any(truth.mount.boresight_deg):
        meta["boresight_deg"] = [float(v) for v in truth.mount.boresight_deg]
    if any(truth.mount.lever_arm_m):
        meta["lever_arm_m"] = [float(v) for v in truth.mount.lever_arm_m]
    if truth.dropped_frames:
        meta["dropped_frames"] = truth.dropped_frames
    if truth.pause_cube is not None:
        meta["pause"] = {"cube": truth.pause_cube, "line": truth.pause_line, "seconds": truth.pause_s}
    if truth.record_turns:
        meta["record_turns"] = True
    if truth.terrain is not None:
        meta["terrain"] = truth.terrain.to_dict()
    if any(truth.gnss_bias_m):
        meta["gnss_bias_m"] = [float(v) for v in truth.gnss_bias_m]
        meta["notes_gnss_bias"] = ("the .lcf positions are the true INS positions + gnss_bias_m (dE, dN, dU metres, "
                                   "grid east/north of epsg, up); poses in this truth are TRUE")
    if truth.ground_changes:
        meta["ground_changes"] = float(truth.ground_changes)
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
    mount = Mount(tuple(float(v) for v in meta.get("boresight_deg", (0.0, 0.0, 0.0))),
                  tuple(float(v) for v in meta.get("lever_arm_m", (0.0, 0.0, 0.0))))
    pause = meta.get("pause")
    return Truth(flight_dir, int(meta["epsg"]), float(meta["fov_deg"]), float(meta["ground_height"]),
                 arrays["wavelengths"], cubes, int(meta["samples"]), tuple(meta["site"]),
                 int(meta["seed"]), scene, Trajectory.from_dict(meta["trajectory"]),
                 sync_offset=float(meta.get("sync_offset", 0.0)), mount=mount,
                 dropped_frames=int(meta.get("dropped_frames", 0)),
                 pause_cube=None if pause is None else int(pause["cube"]),
                 pause_line=None if pause is None else int(pause["line"]),
                 pause_s=0.0 if pause is None else float(pause["seconds"]),
                 record_turns=bool(meta.get("record_turns", False)),
                 terrain=None if meta.get("terrain") is None else Terrain.from_dict(meta["terrain"]),
                 gnss_bias_m=tuple(float(v) for v in meta.get("gnss_bias_m", (0.0, 0.0, 0.0))),
                 ground_changes=float(meta.get("ground_changes", 0.0)))
