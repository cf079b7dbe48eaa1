"""Processing parameters, built once (from the CLI, or by a caller) and passed down explicitly."""

from __future__ import annotations

from dataclasses import dataclass, field

#: Lines whose field-of-view edge looks further than this from nadir (degrees) are left out of the
#: mesh (turns). 23.75 deg is the edge of a level Pika L (47.5 deg field of view); 40 leaves room
#: for wobble and a boresight in straight flight while a banked turn's lines (which would stretch
#: one line over tens of metres to kilometres) are dropped. The default of ``--max-view-angle``.
DEFAULT_MAX_VIEW_ANGLE = 40.0


@dataclass(frozen=True)
class NavigationParams:
    """How navigation is turned into per-line camera poses.

    fov_deg: across-track field of view of the camera, degrees.
    sync_offset: seconds added to every line time before looking up navigation.
    boresight_deg: camera -> body rotation as (roll, pitch, yaw) degrees, aerospace sign, applied
        intrinsically Z-Y-X like the body attitude.
    lever_arm_m: camera position in the body frame (x forward, y right, z down), metres.
    None (sync_offset, boresight_deg, lever_arm_m): not given: what the source recorded, else 0
    (see :meth:`resolved`; sources resolve their parameters when opened).
    """

    fov_deg: float
    sync_offset: float | None = 0.0
    boresight_deg: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
    lever_arm_m: tuple[float, float, float] | None = (0.0, 0.0, 0.0)

    def resolved(self, recorded: dict | None = None) -> NavigationParams:
        """These parameters with every None (not given) replaced by the value a source ``recorded``
        (a collection records what it was ingested with: keys 'sync_offset', 'boresight_deg',
        'lever_arm_m'), else 0."""
        recorded = recorded or {}

        def pick(value, key, default):
            if value is not None:
                return value
            got = recorded.get(key)
            return default if got is None else (tuple(float(v) for v in got) if isinstance(got, list | tuple)
                                                else float(got))

        return NavigationParams(
            fov_deg=self.fov_deg,
            sync_offset=float(pick(self.sync_offset, "sync_offset", 0.0)),
            boresight_deg=tuple(float(v) for v in pick(self.boresight_deg, "boresight_deg", (0.0, 0.0, 0.0))),
            lever_arm_m=tuple(float(v) for v in pick(self.lever_arm_m, "lever_arm_m", (0.0, 0.0, 0.0))))


@dataclass(frozen=True)
class RenderParams:
    """What to render and how.

    gsd: output pixel size, metres.
    ground_height: flat ground height, metres above the ellipsoid; None means automatic.
    mode: 'raw' | 'relative' | 'radiance' | 'reflectance'.
    bands: band indices (0-based) to render, in output order; None means all bands.
    overlap: 'last' (the later line wins) or 'mean'.
    """

    gsd: float
    ground_height: float | None = None
    mode: str = "radiance"
    bands: tuple[int, ...] | None = None
    overlap: str = "last"
    navigation: NavigationParams = field(default_factory=lambda: NavigationParams(fov_deg=47.5))
