"""The downwelling files of a raw flight directory: one ``.spec`` per cube (found by name beside it,
:func:`archive.formats.spec.downwelling_name`) and the spectrometer's ``*.dcp`` (in the directory, or
``--irradiance-calibration``). Found at open (names only), read on first use."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from archive.errors import InputError, MissingInputError
from archive.formats.spec import downwelling_name, read_dcp, read_spec
from archive.sources.irradiance import CubeIrradiance, SkyIrradiance, to_bands

__all__ = ["DownwellingFiles", "reflectance_record"]


@lru_cache(maxsize=16)
def _read(files: DownwellingFiles, token: tuple, first_times: tuple, bands_nm: tuple, fwhm_nm) -> SkyIrradiance:
    return files._read(first_times, bands_nm, fwhm_nm)


@dataclass(frozen=True)
class DownwellingFiles:
    """specs: per cube, its expected ``.spec`` path (None when the cube's name is not Resonon's);
    found: per cube, whether it exists; calibration: the ``.dcp`` (None: none found, or several:
    ``ambiguous`` names them, refused when read)."""

    directory: Path
    specs: tuple[Path | None, ...]
    found: tuple[bool, ...]
    calibration: Path | None
    ambiguous: tuple[str, ...] = ()

    @classmethod
    def find(cls, directory: Path, bases: Sequence[str], calibration: str | os.PathLike | None = None) -> DownwellingFiles:
        """Look for each cube's spectrum and the pack (names only); MissingInputError for a
        ``calibration`` that is not a file."""
        specs = tuple(None if downwelling_name(b) is None else directory / downwelling_name(b) for b in bases)
        found = tuple(p is not None and p.is_file() for p in specs)
        if calibration is not None:
            cal = Path(calibration)
            if not cal.is_file():
                raise MissingInputError(cal, "downwelling calibration (.dcp)", "check --irradiance-calibration")
        else:
            dcps = sorted(p for p in directory.iterdir() if p.is_file() and p.suffix.lower() == ".dcp")
            cal = dcps[0] if len(dcps) == 1 else None
            if len(dcps) > 1:   # refused when reflectance needs one, not when rendering radiance
                return cls(directory, specs, found, None, tuple(p.name for p in dcps))
        return cls(directory, specs, found, cal)

    @property
    def present(self) -> bool:
        """Whether the flight has any downwelling spectrum."""
        return any(self.found)

    def token(self) -> tuple:
        """What reflectance depends on: the files by name, size and modification time."""
        files = [p for p, f in zip(self.specs, self.found, strict=True) if f]
        files += [self.calibration] if self.calibration is not None else []
        return tuple((str(p), p.stat().st_size, p.stat().st_mtime_ns) for p in files)

    def read(self, first_times: Sequence[float], bands_nm, fwhm_nm) -> SkyIrradiance:
        """Every cube's spectrum converted and resampled (:func:`archive.sources.irradiance.to_bands`),
        stamped at ``first_times`` (.lcf s of each cube's first line). A cube without its spectrum,
        or a flight with spectra and no pack, is refused naming the file. Read once per process for
        the same files (names, sizes, modification times) and arguments: every render task of a
        flight unpickles its own source, and parsing three 2048-value headers costs ~20 ms."""
        return _read(self, self.token(), tuple(float(t) for t in first_times), tuple(bands_nm),
                     None if fwhm_nm is None else tuple(fwhm_nm))

    def _read(self, first_times: Sequence[float], bands_nm, fwhm_nm) -> SkyIrradiance:
        for path, found in zip(self.specs, self.found, strict=True):
            if not found:
                what = "downwelling spectrum (.spec)" if path is not None else "downwelling spectrum"
                raise MissingInputError(path if path is not None else self.directory, what,
                                        "every cube needs <ImageSetName>_downwelling_<k>_pre.spec(.hdr) beside "
                                        "it; or pass --white-reference FILE, or use --mode radiance")
        if self.ambiguous:
            raise InputError(self.directory, f"{len(self.ambiguous)} downwelling calibrations: "
                             f"{', '.join(self.ambiguous)}", "pass --irradiance-calibration to choose one")
        if self.calibration is None:
            raise MissingInputError(self.directory / "*.dcp", "downwelling calibration (.dcp)",
                                    "copy the spectrometer's .dcp into the flight directory or pass "
                                    "--irradiance-calibration FILE.dcp")
        cal = read_dcp(self.calibration)
        cubes = []
        for path, t in zip(self.specs, first_times, strict=True):
            x, shift, found = to_bands(read_spec(path), cal, bands_nm, fwhm_nm)
            cubes.append(CubeIrradiance(str(path), float(t), x, shift, found))
        return SkyIrradiance(tuple(cubes), str(self.calibration))


def reflectance_record(sources, white_reference: str | None, panels: str | None = None) -> dict:
    """What a reflectance output was divided by, for its STAC Item (``archive:reflectance``): the
    white reference file, or per flight the sky spectrometer's QA
    (:meth:`archive.sources.irradiance.SkyIrradiance.qa`: per cube the change of irradiance within it,
    whether it passes the threshold, the fraction of lines under low irradiance, the separable
    form's error, the Fraunhofer wavelength check)."""
    if white_reference:
        return {"source": "white_reference", "file": str(white_reference)}
    if panels:   # the empirical line: its fit per flight (a, c per band of the flight)
        return {"source": "panels", "file": str(panels),
                "flights": [{"id": s.id, "bands": sorted(s.fit), "a": [s.fit[b][0] for b in sorted(s.fit)],
                             "c": [s.fit[b][1] for b in sorted(s.fit)], "panel_pixels": s.line.pixels.tolist()}
                            for s in sources]}
    flights = []
    for s in sources:
        sky = getattr(s, "sky", None)
        if sky is None:
            continue
        qa = sky().qa([s.line_times(i) for i in range(len(s.cubes))])
        flights.append({"id": s.id, **qa})
    changed = sum(c["changed"] for f in flights for c in f["cubes"])
    low = max((c["low_fraction"] for f in flights for c in f["cubes"]), default=0.0)
    return {"source": "downwelling", "flights": flights,
            "summary": {"cubes_irradiance_changed": changed, "max_low_irradiance_fraction": low,
                        "max_separable_error": max((c["separable_error"] for f in flights for c in f["cubes"]),
                                                   default=0.0)}}
