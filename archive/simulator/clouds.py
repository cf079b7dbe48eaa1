"""``archive simulate --clouds``: a sky that changes during the flight, what the kit's downwelling
spectrometer records of it, and the truth reflectance.

The sky's brightness ``c(t)`` (a factor on the scene's radiance, 1 = clear) is drawn at each cube's
first line (its spectrometer reading, as Resonon's recorder takes one ``_pre`` spectrum per cube) and
varies linearly in time between those readings, held after the last: 1.0, 0.7, 0.85, 1.0, ... (a
cloud passing: radiance drifts 30 % within cubes). By default it is grey (all wavelengths alike), so
the irradiance the renderer rebuilds is exact up to resampling; ``colour`` tilts every other stamp's
spectrum, so the renderer's separable form (spectrum x factor per cube) is an approximation whose
recorded error the tests check against the truth.

Files written into the flight directory (Resonon's layout, DESIGN 11): per cube
``sim_downwelling_<k>_pre.spec`` + ``.spec.hdr`` (2048 float64 raw counts, ``shutter`` ms) and
``downwelling.dcp`` (gain.spec float64, offset.spec float32, shutter 5.7 ms); the truth's
``clouds.json`` (stamps in GPS s and factors). Truth reflectance = scene radiance / illumination
(:func:`truth_reflectance`), whatever the sky.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from archive.errors import MissingInputError
from archive.formats.spec import IrradianceCalibration, write_dcp, write_spec
from archive.simulator.scene import illumination

__all__ = ["CLOUD_FACTORS", "Clouds", "DCP_NAME", "SPEC_PIXELS", "load_clouds", "spectrometer_wavelengths",
           "truth_reflectance", "write_downwelling"]

CLOUD_FACTORS = (1.0, 0.7, 0.85)  #: sky brightness at consecutive cubes' first lines, cycled
SPEC_PIXELS = 2048              #: Flame pixels
SPEC_SHUTTER_CAL = 5.7          #: ms, the pack's calibration shutter
SPEC_SHUTTER = 8.0              #: ms, the spectra's shutter
SPEC_OFFSET = 1500.0            #: counts of the dark offset
DCP_NAME = "downwelling.dcp"


def spectrometer_wavelengths() -> np.ndarray:
    """(2048,) nm: a Flame's grid, 339.7 nm to 1024.5 nm, slightly quadratic as the real pack's."""
    i = np.arange(SPEC_PIXELS, dtype=float)
    b = 0.383
    c = (1024.49 - 339.708 - b * (SPEC_PIXELS - 1)) / (SPEC_PIXELS - 1) ** 2
    return np.round(339.708 + b * i + c * i**2, 3)


class Clouds:
    """The sky: brightness ``factors`` and colour ``tilts`` at stamps (GPS s), linear between, held
    outside. At time t and wavelength lam (nm) the illumination is multiplied by
    ``factor(t) * (1 + tilt(t) * (lam - 700) / 300)`` (tilt 0: grey)."""

    def __init__(self, stamps, factors, tilts=None):
        self.stamps = np.asarray(stamps, float)
        self.factors = np.asarray(factors, float)
        self.tilts = np.zeros_like(self.factors) if tilts is None else np.asarray(tilts, float)

    @classmethod
    def for_cubes(cls, first_times, colour: float = 0.0) -> Clouds:
        """One stamp per cube at its first line's true time, factors :data:`CLOUD_FACTORS` cycled;
        ``colour``: the tilt of every other stamp (0: a grey sky; 0.04: the sky 4 % bluer at 400 nm
        and 4 % redder at 1000 nm under the cloud, so consecutive spectra differ in shape)."""
        n = len(first_times)
        return cls(first_times, [CLOUD_FACTORS[k % len(CLOUD_FACTORS)] for k in range(n)],
                   [colour * (k % 2) for k in range(n)])

    def factor(self, t) -> np.ndarray:
        """(n,) brightness at GPS times ``t`` (s)."""
        return np.interp(np.asarray(t, float), self.stamps, self.factors)

    def field(self, t, wavelengths) -> np.ndarray:
        """(n, bands) multiplier of the illumination at times ``t`` (s) and ``wavelengths`` (nm)."""
        tilt = np.interp(np.asarray(t, float), self.stamps, self.tilts)
        lam = (np.asarray(wavelengths, float) - 700.0) / 300.0
        return self.factor(t)[:, None] * (1.0 + tilt[:, None] * lam[None, :])


def _sensitivity(wl: np.ndarray) -> np.ndarray:
    """Microflicks per count at the calibration shutter: a smooth Flame-like curve."""
    return 0.8 + 3.0 * ((wl - 650.0) / 350.0) ** 2


def write_downwelling(directory: str | os.PathLike, bases, clouds: Clouds) -> None:
    """The spectra of cubes ``bases`` (``sim_Pika_L_<k>``), the pack and ``truth/clouds.json``
    into ``directory`` (the flight's temporary directory)."""
    directory = Path(directory)
    wl = spectrometer_wavelengths()
    gain = _sensitivity(wl)
    offset = np.full(SPEC_PIXELS, SPEC_OFFSET, np.float32)
    write_dcp(directory / DCP_NAME, IrradianceCalibration(None, gain, offset.astype(float), wl, SPEC_SHUTTER_CAL))
    for base, t in zip(bases, clouds.stamps, strict=True):
        x = illumination(wl) * clouds.field([t], wl)[0]            # white-panel radiance, microflicks
        raw = x / (gain * (SPEC_SHUTTER_CAL / SPEC_SHUTTER)) + offset.astype(float)
        k = base.rsplit("_", 1)[1]
        write_spec(directory / f"sim_downwelling_{k}_pre.spec", raw, wl, SPEC_SHUTTER)
    (directory / "truth").mkdir(exist_ok=True)
    (directory / "truth" / "clouds.json").write_text(json.dumps(
        {"stamps_gps_s": clouds.stamps.tolist(), "factors": clouds.factors.tolist(), "tilts": clouds.tilts.tolist(),
         "model": "factor * (1 + tilt * (nm - 700) / 300), each linear between stamps, held outside"}, indent=1),
        encoding="utf-8")


def load_clouds(directory: str | os.PathLike) -> Clouds:
    """The clouds of a ``--clouds`` flight (MissingInputError naming ``truth/clouds.json``)."""
    path = Path(directory) / "truth" / "clouds.json"
    if not path.is_file():
        raise MissingInputError(path, "cloud truth", "simulate the flight with --clouds")
    d = json.loads(path.read_text(encoding="utf-8"))
    return Clouds(d["stamps_gps_s"], d["factors"], d.get("tilts"))


def truth_reflectance(truth, e, n, crs=None) -> np.ndarray:
    """(bands, ...) true reflectance at points (e, n): the scene's radiance (clear sky) divided by
    the illumination (a perfect white reflector's radiance), per band."""
    return truth.radiance(e, n, crs) / illumination(truth.wavelengths).reshape((-1,) + (1,) * np.ndim(e))
