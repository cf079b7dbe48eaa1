"""The simulated pushbroom camera: direct ray tracing of every sample over its footprint and
exposure, and the radiometric model that turns radiance into 12-bit DN.

The camera path is the platform's trajectory, or a :class:`~archive.simulator.mount.MountedCamera`
(boresight, lever arm). Camera vector of focal-plane coordinate u: (0, u, 1);
sample s (0-based, N samples) covers u in [-T + 2T s/N, -T + 2T (s+1)/N] with T = tan(fov/2).
Each sample's DN integrates the radiance over ``ku`` points of u in its interval times ``kt``
points of time in [t_line, t_line + shutter] (midpoint rule), each ray intersected with the flat
ground ``alt = ground_height`` (or its first hit on the flight's terrain, when it has one: the
scene is an orthophoto draped on the terrain, radiance a function of E, N). A ray that does not
meet the ground (pointing at or above the horizon, as in steeply banked turns) sees black sky
(abundance 0).

DN = dark[b, s] + L * response / gain[b, s] + noise, rounded and clipped to 0..4095, with
``response = (shutter / shutter_cal) * 10 ** ((gain_db - gain_cal) / 20)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from archive.simulator.scene import Scene
from archive.simulator.trajectory import Trajectory

__all__ = ["CEILING", "EXPOSURES", "GAIN_CAL", "SHUTTER_CAL", "Radiometry", "band_fwhm", "ground_points",
           "trace_abundance", "make_radiometry"]

CEILING = 4095
SHUTTER_CAL = 3.0   #: ms, reference exposure of the calibration
GAIN_CAL = 0.0      #: dB
#: (shutter ms, gain dB) cycled over cubes; responses 1.0, 1.18, 1.3, 1.73
EXPOSURES = ((3.0, 0.0), (2.5, 3.0), (3.9, 0.0), (2.6, 6.0))
WHITE_DN = 2000.0   #: DN of the white panel (reflectance 0.9) at the reference exposure, peak band
NOISE_DN = 1.0      #: Gaussian read noise, DN
#: Spectral FWHM (nm) of an unbinned Pika L band at 400 nm and at 1000 nm (linear in between).
FWHM_NATIVE_NM = (2.5, 3.0)


def band_fwhm(wavelengths: np.ndarray) -> np.ndarray:
    """(bands,) spectral full width at half maximum in nm of bands centred at ``wavelengths`` (nm).

    A Pika L band is 2.5 nm wide at 400 nm, 3.0 nm at 1000 nm; a simulated sensor with fewer
    bands is a spectrally binned one, whose bands are as wide as their spacing when that is larger.
    Only the headers' ``fwhm`` uses it: the scene's spectra are sampled at the centres.
    """
    lam = np.asarray(wavelengths, float)
    lo, hi = FWHM_NATIVE_NM
    native = lo + (hi - lo) * np.clip((lam - 400.0) / 600.0, 0.0, 1.0)
    spacing = np.abs(np.gradient(lam)) if lam.size > 1 else np.zeros_like(lam)
    return np.round(np.maximum(native, spacing), 3)


# Standard normal quantiles at 65536 equally likely levels: indexing it with uniform 16-bit integers
# draws (quantised) Gaussian noise ~3x faster than Generator.standard_normal, which dominated the
# cost of paper-size cubes; the DN is rounded to whole numbers afterwards anyway.
_NORMAL = (ndtri((np.arange(65536) + 0.5) / 65536) * NOISE_DN).astype(np.float32)


def _gaussian(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Gaussian noise (float32, sigma NOISE_DN DN) of ``shape``."""
    return _NORMAL[rng.integers(0, 65536, int(np.prod(shape)), dtype=np.uint16)].reshape(shape)


def response(shutter_ms: float, gain_db: float) -> float:
    return (shutter_ms / SHUTTER_CAL) * 10.0 ** ((gain_db - GAIN_CAL) / 20.0)


@dataclass(frozen=True, eq=False)
class Radiometry:
    """gain (bands, samples): radiance per DN at the reference exposure; darks: {(gain_db,
    shutter_ms): (bands, samples) integer-valued float64 DN}."""

    gain: np.ndarray
    darks: dict[tuple[float, float], np.ndarray]

    def dn(self, radiance: np.ndarray, shutter_ms: float, gain_db: float,
           rng: np.random.Generator) -> np.ndarray:
        """radiance (bands, lines, samples) -> uint16 DN (bands, lines, samples)."""
        dark = self.darks[(gain_db, shutter_ms)]
        scale = (response(shutter_ms, gain_db) / self.gain).astype(np.float32)
        value = np.multiply(radiance, scale[:, None, :], dtype=np.float32)
        value += dark.astype(np.float32)[:, None, :]
        value += _gaussian(rng, value.shape)
        np.rint(value, out=value)
        np.clip(value, 0, CEILING, out=value)
        return value.astype(np.uint16)


def make_radiometry(white_spectrum: np.ndarray, wavelengths: np.ndarray, samples: int,
                    exposures: list[tuple[float, float]], rng: np.random.Generator) -> Radiometry:
    """A plausible calibration: vignetting (+12 % radiance per DN at the swath edges), a smooth
    spectral sensitivity, 0.5 % pixel-to-pixel variation; dark frames ~100 +- 10 DN per (band,
    sample), slightly different per (gain, shutter)."""
    lam = np.asarray(wavelengths, float)
    bands = lam.size
    pos = (np.arange(samples) + 0.5) / samples * 2.0 - 1.0
    vignetting = 1.0 + 0.12 * pos**2
    sensitivity = 0.65 + 0.35 * np.exp(-0.5 * ((lam - 650.0) / 200.0) ** 2)
    gain = (np.asarray(white_spectrum, float)[:, None] / (WHITE_DN * sensitivity[:, None])
            * vignetting[None, :] * (1.0 + 0.005 * rng.standard_normal((bands, samples))))
    pattern = 100.0 + 8.0 * rng.standard_normal((bands, samples))
    darks = {}
    for shutter, gain_db in sorted(set(exposures)):
        extra = 0.5 * gain_db + 0.3 * shutter + rng.standard_normal((bands, samples))
        darks[(gain_db, shutter)] = np.clip(np.rint(pattern + extra), 0, CEILING)
    return Radiometry(gain, darks)


def focal_plane(fov_deg: float, samples: int, ku: int) -> np.ndarray:
    """u of every sub-sample, (samples * ku,) ordered sample-major."""
    t = math.tan(math.radians(fov_deg) / 2.0)
    frac = (np.arange(samples)[:, None] + (np.arange(ku)[None, :] + 0.5) / ku) / samples
    return (-t + 2.0 * t * frac).ravel()


def ground_points(traj: Trajectory, t: np.ndarray, u: np.ndarray,
                  terrain=None) -> tuple[np.ndarray, np.ndarray]:
    """UTM E, N (m), each (len(t), len(u)), where the rays of focal-plane coordinates ``u`` at GPS
    times ``t`` meet the ground (``traj.ground_height``, or the first hit on ``terrain``, a
    :class:`~archive.simulator.terrain.Terrain`); NaN for rays that do not go down.
    ``traj``: the camera path (a Trajectory when camera = body, or a MountedCamera)."""
    t = np.asarray(t, float).ravel()
    pos = traj.position(t)
    r = traj.attitude(t).as_matrix()                               # (n, 3, 3) camera -> NED
    d = r[:, None, :, 1] * u[None, :, None] + r[:, None, :, 2]     # (n, U, 3) N, E, D
    if terrain is not None:
        shape = d.shape[:2]
        origin = np.broadcast_to(pos[:, None, :], shape + (3,)).reshape(-1, 3)
        lam = terrain.intersect(origin, d.reshape(-1, 3)).reshape(shape)
        return pos[:, 0, None] + lam * d[..., 1], pos[:, 1, None] + lam * d[..., 0]
    down = d[..., 2] > 1e-9
    if not down.all():
        d = np.where(down[..., None], d, np.nan)
    lam = (pos[:, 2] - traj.ground_height)[:, None] / d[..., 2]
    return pos[:, 0, None] + lam * d[..., 1], pos[:, 1, None] + lam * d[..., 0]


def trace_abundance(scene: Scene, traj: Trajectory, line_time: np.ndarray, shutter_s: float,
                    fov_deg: float, samples: int, ku: int, kt: int, terrain=None) -> np.ndarray:
    """Abundances (materials, lines, samples) integrated over each sample's footprint and exposure
    (each sub-ray's first hit on ``terrain`` when given, else on the flat ground)."""
    line_time = np.asarray(line_time, float)
    t = line_time[:, None] + shutter_s * (np.arange(kt)[None, :] + 0.5) / kt   # (lines, kt)
    u = focal_plane(fov_deg, samples, ku)
    e, n = ground_points(traj, t.ravel(), u, terrain)
    sky = ~np.isfinite(e)
    if sky.any():
        e, n = np.where(sky, scene.origin_e, e), np.where(sky, scene.origin_n, n)
    a = scene.abundance(e, n)                                       # (M, lines*kt, samples*ku)
    if sky.any():
        a[:, sky] = 0.0
    a = a.reshape(a.shape[0], line_time.size, kt, samples, ku)
    return a.mean(axis=(2, 4))
