"""Downwelling irradiance per image line, from the kit's sky spectrometer (DESIGN 11).

Each cube's raw spectrum (:mod:`archive.formats.spec`) becomes ``X`` = the radiance of a white
Lambertian panel under that sky (microflicks, the camera's radiance unit; E = pi * X * 1e-5
W m-2 nm-1), is resampled onto the camera's bands (a Gaussian of each band's FWHM over the
spectrometer's pixels) and stamped at its cube's first line (.lcf time scale, sync offset included).
Between stamps ``X`` is interpolated linearly in time, per band; after the last stamp (and before the
first) it is held. Reflectance = L / X = pi L / E.

The band pass divides by ``gain`` per (band, sample) and ``response`` per line, so the renderer
carries ``X(line, band)`` as the separable product ``spectrum(band) * factor(line)``, per cube:
``spectrum`` = the cube's mean ``X`` over its lines, ``factor(line)`` = the mean over bands of
``X(line, band) / spectrum(band)``. Exact when the sky changes in brightness only (spectra
proportional: the simulator's clouds); otherwise its largest relative error over the cube's lines and
bands is computed, recorded (:attr:`CubeIrradiance.separable_error`) and warned about above
:data:`SEPARABLE_WARN` (README: a 4 % change of the spectrum's shape between two cubes costs 1.0-1.2 %).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from archive.errors import InputError
from archive.formats.spec import IrradianceCalibration, Spectrum

__all__ = ["CubeIrradiance", "FRAUNHOFER_NM", "LOW_IRRADIANCE", "SEPARABLE_WARN", "SHIFT_WARN_NM",
           "SkyIrradiance", "band_weights", "fraunhofer_shift", "implausible_bands", "separable", "sun_panel_radiance",
           "to_bands"]

#: Solar absorption lines (nm) used to check the spectrometer's wavelengths (air wavelengths).
FRAUNHOFER_NM = (430.78, 486.13, 518.36, 589.30, 656.28, 686.72, 760.30)
#: |shift| (nm) above which the wavelength check warns (and corrects the wavelengths).
SHIFT_WARN_NM = 0.5
#: Relative error of the separable (spectrum x factor) form above which a cube is warned about.
SEPARABLE_WARN = 0.005
#: QA: X below this fraction of the flight's median (per band, averaged) flags a line "low irradiance".
LOW_IRRADIANCE = 0.25
#: QA: a change of X within a cube beyond this fraction flags the cube "irradiance changed".
CHANGE_WARN = 0.10
#: Physical sense of X per band, as fractions of :func:`sun_panel_radiance` (a white panel facing the sun
#: above the atmosphere): below LOW the sky is darker than deep twilight, above HIGH brighter than the sun.
PLAUSIBLE_LOW, PLAUSIBLE_HIGH = 1e-3, 1.5
#: A band whose X exceeds SPIKE x the median of its neighbours (5 bands each side) is a spike: the sky has
#: no emission lines (absorption dips, O2 and water, are real and allowed).
SPIKE = 3.0


def sun_panel_radiance(bands_nm: Sequence[float]) -> np.ndarray:
    """(bands,) radiance of a white Lambertian panel facing the sun above the atmosphere, microflicks:
    the sun as a 5772 K black body seen at 1 au (B(lambda, T) * (R_sun / au)^2), the upper bound of any
    downwelling X (the atmosphere only takes away)."""
    from scipy.constants import astronomical_unit, c, h, k

    lam = np.asarray(bands_nm, float) * 1e-9
    planck = 2 * h * c ** 2 / lam ** 5 / np.expm1(h * c / (lam * k * 5772.0))   # W m-2 sr-1 m-1
    return planck * (6.957e8 / astronomical_unit) ** 2 * 1e-9 * 1e5   # per nm, in microflicks (1e-5 W m-2 sr-1 nm-1)


def implausible_bands(x: np.ndarray, bands_nm: Sequence[float]) -> list[tuple[float, str]]:
    """(band nm, why) for each band of X (bands,) that makes no physical sense: not finite, not within
    [:data:`PLAUSIBLE_LOW`, :data:`PLAUSIBLE_HIGH`] x :func:`sun_panel_radiance`, or a spike."""
    x = np.asarray(x, float)
    sun = sun_panel_radiance(bands_nm)
    out = []
    for b, (v, top) in enumerate(zip(x, sun, strict=True)):
        near = np.concatenate([x[max(0, b - 5):b], x[b + 1:b + 6]])
        if not np.isfinite(v):
            out.append((float(bands_nm[b]), "not a number"))
        elif v < PLAUSIBLE_LOW * top:
            out.append((float(bands_nm[b]), f"{v:.3g} below {PLAUSIBLE_LOW * top:.3g}"))
        elif v > PLAUSIBLE_HIGH * top:
            out.append((float(bands_nm[b]), f"{v:.3g} above the sun's {top:.3g}"))
        elif near.size >= 2 and v > SPIKE * np.median(near):
            out.append((float(bands_nm[b]), f"a spike ({v / np.median(near):.1f} x its neighbours)"))
    return out


def band_weights(wavelengths: np.ndarray, bands_nm: Sequence[float], fwhm_nm: Sequence[float] | None) -> np.ndarray:
    """(bands, pixels) weights (rows sum to 1) resampling a spectrum sampled at ``wavelengths`` (nm,
    increasing) onto camera bands centred at ``bands_nm`` with Gaussian responses of ``fwhm_nm``
    (None: each band as wide as the band spacing). Each pixel counts with its own width. InputError
    when a band lies outside the spectrometer's range."""
    wl = np.asarray(wavelengths, float)
    centres = np.asarray(bands_nm, float)
    if fwhm_nm is None:
        fwhm = np.abs(np.gradient(centres)) if centres.size > 1 else np.full(1, 3.0)
    else:
        fwhm = np.asarray(fwhm_nm, float)
    # never narrower than the spectrometer's own pixels (else a band would see no pixel)
    fwhm = np.maximum(fwhm, 2.0 * float(np.max(np.diff(wl))))
    outside = (centres < wl[0]) | (centres > wl[-1])
    if np.any(outside):
        raise InputError(None, f"camera bands {centres[outside].tolist()} nm lie outside the spectrometer's "
                         f"{wl[0]:.1f}-{wl[-1]:.1f} nm", "select bands inside it (--wavelengths), or use "
                         "--white-reference FILE")
    width = np.gradient(wl)
    sigma = fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    w = np.exp(-0.5 * ((wl[None, :] - centres[:, None]) / sigma[:, None]) ** 2) * width[None, :]
    return w / w.sum(axis=1, keepdims=True)


def fraunhofer_shift(wavelengths: np.ndarray, x: np.ndarray, window_nm: float = 3.0,
                     min_depth: float = 0.02) -> tuple[float | None, int]:
    """Estimated wavelength error of a sky spectrum (nm, true minus recorded: add it to the
    recorded wavelengths) and the number of Fraunhofer lines it rests on.

    For each line of :data:`FRAUNHOFER_NM` inside the spectrum, the minimum within ``window_nm`` of
    it is located to sub-pixel precision (a parabola through the minimum and its neighbours) if it
    is at least ``min_depth`` below the straight continuum between the window's ends; the median of
    the line offsets is the shift. (None, 0) when fewer than two lines are found: the spectrum is
    then left as it is (DESIGN 11)."""
    wl = np.asarray(wavelengths, float)
    x = np.asarray(x, float)
    offsets = []
    for line in FRAUNHOFER_NM:
        sel = np.flatnonzero(np.abs(wl - line) <= window_nm)
        if sel.size < 5 or sel[0] == 0 or sel[-1] == wl.size - 1:
            continue
        seg = x[sel]
        cont = np.interp(wl[sel], wl[sel[[0, -1]]], seg[[0, -1]])
        rel = seg / np.where(cont > 0, cont, np.nan)
        if not np.all(np.isfinite(rel)):
            continue
        k = int(np.argmin(rel))
        if 1 - rel[k] < min_depth or k in (0, sel.size - 1):
            continue
        a, b, c = rel[k - 1], rel[k], rel[k + 1]
        den = a - 2 * b + c
        frac = 0.5 * (a - c) / den if den > 0 else 0.0
        i = sel[k]
        found = wl[i] + frac * (wl[i + 1] - wl[i - 1]) / 2.0
        offsets.append(line - found)
    if len(offsets) < 2:
        return None, len(offsets)
    return float(np.median(offsets)), len(offsets)


def separable(x_lines: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """x_lines (lines, bands) -> (spectrum (bands,), factor (lines,), largest relative error of
    ``factor[:, None] * spectrum[None, :]`` against ``x_lines``) (module docstring)."""
    x = np.asarray(x_lines, float)
    spectrum = x.mean(axis=0)
    factor = (x / spectrum[None, :]).mean(axis=1)
    approx = factor[:, None] * spectrum[None, :]
    return spectrum, factor, float(np.max(np.abs(approx / x - 1.0))) if x.size else 0.0


@dataclass(frozen=True, eq=False)
class CubeIrradiance:
    """One cube's sky spectrum on the camera's bands.

    spec: the .spec file it came from; time: .lcf-scale s of the cube's first line (its stamp);
    x_bands: (bands,) X in microflicks (white-panel radiance) on every camera band; shift_nm: the
    Fraunhofer wavelength shift estimated (None: no line found), applied to the wavelengths when
    beyond :data:`SHIFT_WARN_NM`; lines_found: lines it rests on.
    """

    spec: str
    time: float
    x_bands: np.ndarray
    shift_nm: float | None
    lines_found: int


def to_bands(spectrum: Spectrum, calibration: IrradianceCalibration, bands_nm,
             fwhm_nm) -> tuple[np.ndarray, float | None, int]:
    """One raw spectrum as X (bands,) on the camera bands, with its wavelength check
    (:func:`fraunhofer_shift`; corrected and warned about beyond :data:`SHIFT_WARN_NM`) and its physical
    sense (:func:`implausible_bands`: InputError naming the file and the bands)."""
    x = calibration.white_radiance(spectrum)
    wl = spectrum.wavelengths
    shift, found = fraunhofer_shift(wl, x)
    if shift is not None and abs(shift) > SHIFT_WARN_NM:
        warnings.warn(f"{spectrum.path}: the spectrometer's wavelengths are off by {shift:+.2f} nm "
                      f"(Fraunhofer lines, {found} found); corrected", stacklevel=2)
        wl = wl + shift
    if not np.all(np.isfinite(x)) or np.median(x) <= 0:
        raise InputError(spectrum.path, "gives no positive irradiance (offset above the raw counts?)",
                         "check the spectrum and the .dcp (--irradiance-calibration)")
    x_bands = band_weights(wl, bands_nm, fwhm_nm) @ x
    bad = implausible_bands(x_bands, bands_nm)
    if bad:
        shown = "; ".join(f"{nm:.1f} nm: {why}" for nm, why in bad[:4]) + (f"; {len(bad) - 4} more" * (len(bad) > 4))
        raise InputError(spectrum.path, f"gives a sky irradiance that makes no physical sense in {len(bad)} of "
                         f"{len(list(bands_nm))} bands (X in microflicks: {shown})",
                         "check the spectrum and the .dcp (--irradiance-calibration), or pass --white-reference, "
                         "or render --mode radiance")
    return x_bands, shift, found


@dataclass(frozen=True, eq=False)
class SkyIrradiance:
    """A flight's downwelling irradiance: one :class:`CubeIrradiance` per cube, in capture order."""

    cubes: tuple[CubeIrradiance, ...]
    calibration: str

    def per_line(self, times: np.ndarray) -> np.ndarray:
        """(lines, bands) X (microflicks) at ``times`` (.lcf-scale s): linear in time between the cubes'
        stamps, held outside them."""
        t = np.array([c.time for c in self.cubes])
        x = np.stack([c.x_bands for c in self.cubes])          # (cubes, bands)
        order = np.argsort(t, kind="stable")
        t, x = t[order], x[order]
        times = np.asarray(times, float)
        return np.stack([np.interp(times, t, x[:, b]) for b in range(x.shape[1])], axis=1)

    def cube_terms(self, times: np.ndarray, bands: Sequence[int], where: str) -> tuple[np.ndarray, np.ndarray, float]:
        """The renderer's terms for one cube's lines at ``times`` and ``bands``: (spectrum
        (len(bands),), factor (lines,), separable error); warns above :data:`SEPARABLE_WARN`."""
        x = self.per_line(times)[:, list(bands)]
        spectrum, factor, error = separable(x)
        if error > SEPARABLE_WARN:
            warnings.warn(f"{where}: the sky's spectrum changes within the cube; reflectance is off by up "
                          f"to {100 * error:.2f} % (separable irradiance)", stacklevel=2)
        return spectrum, factor, error

    def qa(self, cube_times: Sequence[np.ndarray]) -> dict:
        """QA summary: per cube the relative change of X within it (max over bands of
        (max - min) / mean), whether it exceeds :data:`CHANGE_WARN`, the fraction of its lines below
        :data:`LOW_IRRADIANCE` x the flight's median, the largest relative error of the separable
        form over all bands, and the wavelength shifts."""
        per = [self.per_line(t) for t in cube_times]
        median = np.median(np.concatenate(per), axis=0)
        out = []
        for c, x in zip(self.cubes, per, strict=True):
            change = float(np.max((x.max(axis=0) - x.min(axis=0)) / x.mean(axis=0)))
            low = float(np.mean(np.mean(x / median, axis=1) < LOW_IRRADIANCE))
            out.append({"spec": c.spec, "time": c.time, "change": round(change, 6),
                        "separable_error": round(separable(x)[2], 6),
                        "changed": change > CHANGE_WARN, "low_fraction": round(low, 6),
                        "shift_nm": None if c.shift_nm is None else round(c.shift_nm, 4),
                        "fraunhofer_lines": c.lines_found,
                        "x_mean": round(float(np.mean(c.x_bands)), 4)})
        return {"source": "downwelling", "calibration": self.calibration, "cubes": out}
