"""The camera's mounting on the platform: boresight angles and lever arm (DESIGN section 3).

camera -> body = ``Rotation.from_euler('ZYX', [yaw, pitch, roll], degrees=True)`` (aerospace signs:
+roll tilts the view like extra right-wing-down roll, +pitch looks forward); camera -> NED = body -> NED
* camera -> body; camera position = INS position + body -> NED applied to the lever arm (metres in the
body frame: x forward, y right wing, z down). The ``.lcf`` records the INS (body) pose; the camera sees
through :class:`MountedCamera`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["Mount", "MountedCamera", "camera_path"]


@dataclass(frozen=True)
class Mount:
    """``boresight_deg`` (roll, pitch, yaw) degrees and ``lever_arm_m`` (x, y, z) metres, body frame."""

    boresight_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def identity(self) -> bool:
        return not any(self.boresight_deg) and not any(self.lever_arm_m)

    @property
    def rotation(self) -> Rotation:
        """camera -> body."""
        roll, pitch, yaw = (float(v) for v in self.boresight_deg)
        return Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True)


class MountedCamera:
    """Camera poses of a platform (anything with ``position(t)``, ``attitude(t)`` and
    ``ground_height``, e.g. a :class:`~archive.simulator.trajectory.Trajectory`) seen through ``mount``.
    Positions are (..., 3) E, N (UTM m), altitude (m); attitudes camera -> NED (grid north)."""

    def __init__(self, platform, mount: Mount):
        self.platform = platform
        self.mount = mount
        self._rotation = mount.rotation
        self._lever = np.asarray(mount.lever_arm_m, float)

    @property
    def ground_height(self) -> float:
        return self.platform.ground_height

    def position(self, t) -> np.ndarray:
        t = np.asarray(t, float)
        pos = self.platform.position(t)
        if not self._lever.any():
            return pos
        ned = self.platform.attitude(t.ravel()).apply(self._lever).reshape(t.shape + (3,))
        return pos + np.stack([ned[..., 1], ned[..., 0], -ned[..., 2]], axis=-1)

    def attitude(self, t) -> Rotation:
        body = self.platform.attitude(t)
        return body * self._rotation if any(self.mount.boresight_deg) else body

    def __call__(self, t) -> tuple[np.ndarray, Rotation]:
        t = np.atleast_1d(np.asarray(t, float))
        return self.position(t), self.attitude(t)


def camera_path(platform, mount: Mount):
    """``platform`` itself when the mount is the identity (so that the default flight's numbers do not
    change by a bit), else a :class:`MountedCamera`."""
    return platform if mount.identity else MountedCamera(platform, mount)
