"""Processing parameters, built once (from the CLI, or by a caller) and passed down explicitly."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from archive.overlap import LAST, OverlapRule

#: Lines whose field-of-view edge looks further than this from nadir (degrees) are left out of the
#: mesh (turns). 23.75 deg is the edge of a level Pika L (47.5 deg field of view); 40 leaves room
#: for wobble and a boresight in straight flight while a banked turn's lines (which would stretch
#: one line over tens of metres to kilometres) are dropped. The default of ``--max-view-angle``.
DEFAULT_MAX_VIEW_ANGLE = 40.0


@dataclass(frozen=True)
class NavigationParams:
    """How navigation is turned into per-line camera poses (no field of view: poses do not depend on
    it; the meshes' one is the render's :class:`MeshSpec`).

    sync_offset: seconds added to every line time before looking up navigation.
    boresight_deg: camera -> body rotation as (roll, pitch, yaw) degrees, aerospace sign, applied
        intrinsically Z-Y-X like the body attitude.
    lever_arm_m: camera position in the body frame (x forward, y right, z down), metres.
    position_offset_m: (dE, dN, dU) metres added to every INS position of the flight before the
        lever arm: grid east and north of the flight's UTM zone, and up (ellipsoidal); what
        ``archive calibrate --reference`` estimates (a GNSS bias relative to another flight, DESIGN 11).
    None (sync_offset, boresight_deg, lever_arm_m, position_offset_m): not given: what the source
    recorded, else 0 (see :meth:`resolved`; sources resolve their parameters when opened; a position
    offset neither given nor recorded stays None, which means none).
    """

    sync_offset: float | None = 0.0
    boresight_deg: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
    lever_arm_m: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
    position_offset_m: tuple[float, float, float] | None = None

    def resolved(self, recorded: dict | None = None) -> NavigationParams:
        """These parameters with every None (not given) replaced by the value a source ``recorded``
        (a collection records what it was ingested with: keys 'sync_offset', 'boresight_deg',
        'lever_arm_m', and after a co-registration 'position_offset_m': see
        :func:`recorded_navigation`), else 0."""
        recorded = recorded or {}

        def pick(value, key, default):
            if value is not None:
                return value
            got = recorded.get(key)
            return default if got is None else (tuple(float(v) for v in got) if isinstance(got, list | tuple)
                                                else float(got))

        return NavigationParams(
            sync_offset=float(pick(self.sync_offset, "sync_offset", 0.0)),
            boresight_deg=tuple(float(v) for v in pick(self.boresight_deg, "boresight_deg", (0.0, 0.0, 0.0))),
            lever_arm_m=tuple(float(v) for v in pick(self.lever_arm_m, "lever_arm_m", (0.0, 0.0, 0.0))),
            position_offset_m=self._offset(recorded))

    def _offset(self, recorded: dict) -> tuple[float, float, float] | None:
        """The position offset given, else the recorded one, else None (none: zero)."""
        if self.position_offset_m is not None:
            return tuple(float(v) for v in self.position_offset_m)
        got = recorded.get("position_offset_m")
        return None if got is None else tuple(float(v) for v in got)

    @property
    def position_offset(self) -> tuple[float, float, float]:
        """(dE, dN, dU) metres, 0 where not given."""
        return (0.0, 0.0, 0.0) if self.position_offset_m is None else tuple(float(v) for v in self.position_offset_m)


def recorded_navigation(attrs: dict) -> dict:
    """The navigation parameters a collection records (its group attributes ``attrs``):
    ``navigation_params`` (what ingest and ``calibrate --apply`` write), plus the position offset of
    a co-registration (``archive calibrate --reference``), which is kept in the calibration note
    ``navigation_calibration`` ('position_offset_m', 'relative_to')."""
    out = dict(attrs.get("navigation_params") or {})
    note = attrs.get("navigation_calibration") or {}
    if isinstance(note, dict) and note.get("position_offset_m") is not None:
        out["position_offset_m"] = [float(v) for v in note["position_offset_m"]]
    return out


@dataclass(frozen=True)
class RenderParams:
    """What to render and how.

    gsd: output pixel size, metres (the ground, field of view and view-angle limit are the
    render's :class:`MeshSpec`).
    mode: 'raw' | 'relative' | 'radiance' | 'reflectance'.
    bands: band indices (0-based) to render, in output order; None means all bands.
    overlap: the overlap rule (:mod:`archive.overlap`).
    """

    gsd: float
    mode: str = "radiance"
    bands: tuple[int, ...] | None = None
    overlap: OverlapRule = LAST
    navigation: NavigationParams = field(default_factory=NavigationParams)


@dataclass(frozen=True)
class MeshSpec:
    """How the cube meshes of a render are built: decided once (:func:`archive.run.pipeline.open_inputs`)
    and passed whole (inputs, output plan, render plan, mesh tasks, graph keys, provenance layers).

    fov_deg: across-track field of view of the camera, degrees.
    ground_height: flat ground height, metres above the ellipsoid; None with a DEM.
    max_view_angle: degrees off nadir at the field-of-view edge beyond which lines are left out of
        the meshes (turns); None: none.
    epsg: EPSG code of the output grid (meshes of another CRS are transformed into it); None: not
        decided yet (``--crs`` not given: the plan takes the UTM zone holding most of the flights,
        :meth:`with_epsg`).
    dem: the :class:`archive.terrain.dem.DemSpec` the meshes follow instead of flat ground, else None.
    gsd: with a DEM, the output pixel size (metres) the terrain segmentation follows; else None.

    A frozen dataclass of plain values (and a DemSpec, itself one): it tokenizes by value, so graph
    keys built from it are the same in every run.
    """

    fov_deg: float
    ground_height: float | None = None
    max_view_angle: float | None = DEFAULT_MAX_VIEW_ANGLE
    epsg: int | None = None
    dem: object = None   #: an archive.terrain.dem.DemSpec (not imported: params is below the terrain layer)
    gsd: float | None = None

    def __post_init__(self):
        if (self.dem is None) == (self.ground_height is None):
            raise ValueError("a MeshSpec has either a flat ground height or a DEM")

    @property
    def flat_ground(self) -> float:
        """The flat ground height (m) the mesh builders take: NaN with a DEM."""
        return math.nan if self.ground_height is None else float(self.ground_height)

    def with_epsg(self, epsg: int) -> MeshSpec:
        """This spec for an output grid in EPSG:``epsg``."""
        return dataclasses.replace(self, epsg=int(epsg))


def coregistration_properties(attrs: dict) -> dict:
    """STAC Item properties of a collection's recorded co-registration (its group attributes
    ``attrs``): ``archive:coregistration`` = {'relative_to', 'position_offset_m', 'sigma',
    'residual_px_between', 'date'}; {} when it was never co-registered."""
    note = attrs.get("navigation_calibration") or {}
    if not isinstance(note, dict) or note.get("position_offset_m") is None:
        return {}
    params = attrs.get("navigation_params") or {}
    return {"archive:coregistration": {
        "relative_to": note.get("relative_to"), "position_offset_m": note["position_offset_m"],
        "sync_offset_s": params.get("sync_offset"), "boresight_deg": params.get("boresight_deg"),
        "sigma": note.get("sigma"), "residual_px_between": note.get("residual_px_between"),
        "date": note.get("date")}}
