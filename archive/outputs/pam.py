"""Band names of a Zarr output as GDAL shows them: a GDAL PAM sidecar (``.aux.xml``) inside the store.

GDAL's Zarr driver exposes a (band, y, x) array (a stack's (time, band, y, x)) as a raster whose
bands are the array's slices along the other dimensions; it gives them no description of its own,
but reads the band descriptions and metadata of its *persistent auxiliary metadata* (PAM) file,
``<array>/.zarray.aux.xml`` (Zarr v2), section ``AsClassicDataset(<x>,<y>) view of /<array>``
(the file and section GDAL itself writes when a band description is set through
``rasterio.open(..., "r+")``; tests/test_ecosystem.py reads it back with rasterio).
:func:`write_band_pam` writes that file when the store is created, so that ``gdalinfo``, rasterio
(``.descriptions``) and QGIS show "650.0 nm" and, in GDAL's IMAGERY domain,
``CENTRAL_WAVELENGTH_UM`` / ``FWHM_UM`` per band, as in the COG. zarr and xarray ignore the file
(not a Zarr key). Zarr v3 stores get none: the GDAL 3.10 of rasterio's wheel does not read their
codecs.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

__all__ = ["BandText", "band_texts", "pam_path", "write_band_pam"]

#: One band's text: (description, default-domain metadata items, IMAGERY-domain items).
BandText = tuple[str, dict[str, str], dict[str, str]]


def _micrometres(nm: float) -> str:
    return f"{nm / 1000.0:.7f}".rstrip("0").rstrip(".")


def band_texts(labels: Sequence[str], wavelengths: Sequence[float] | None,
               fwhm: Sequence[float] | None) -> list[BandText]:
    """Per band (in order): its description ``labels[b]`` ("650.0 nm"), the items ``wavelength``,
    ``wavelength_units`` (nm) and ``fwhm`` (nm) where known, and GDAL's standard IMAGERY items
    ``CENTRAL_WAVELENGTH_UM`` / ``FWHM_UM`` (micrometres), the items the COG's bands carry."""
    out = []
    for b, label in enumerate(labels):
        items: dict[str, str] = {}
        imagery: dict[str, str] = {}
        if wavelengths is not None:
            items.update(wavelength=f"{float(wavelengths[b]):.4f}", wavelength_units="nm")
            imagery["CENTRAL_WAVELENGTH_UM"] = _micrometres(float(wavelengths[b]))
        if fwhm is not None:
            items["fwhm"] = f"{float(fwhm[b]):.4f}"
            imagery["FWHM_UM"] = _micrometres(float(fwhm[b]))
        out.append((str(label), items, imagery))
    return out


def pam_path(store: str | os.PathLike, array: str) -> Path:
    """The PAM file GDAL reads for array ``array`` of the Zarr v2 store ``store``."""
    return Path(store) / array / ".zarray.aux.xml"


def write_band_pam(store: str | os.PathLike, array: str, ndim: int, bands: Sequence[BandText]) -> Path:
    """Write the PAM file of array ``array`` (``ndim`` dimensions, the last two y and x) of the
    Zarr v2 store ``store``: one ``PAMRasterBand`` per entry of ``bands`` (GDAL's band order: the
    non-spatial dimensions row-major, e.g. time-major for a stack). Replaces an older file (written
    under a temporary name, renamed). Returns its path."""
    from archive.files import write_atomic

    root = ET.Element("PAMDataset")
    derived = ET.SubElement(root, "DerivedDataset",
                            name=f"AsClassicDataset({ndim - 1},{ndim - 2}) view of /{array}")
    dataset = ET.SubElement(derived, "PAMDataset")
    for k, (description, items, imagery) in enumerate(bands):
        band = ET.SubElement(dataset, "PAMRasterBand", band=str(k + 1))
        ET.SubElement(band, "Description").text = description
        for domain, values in ((None, items), ("IMAGERY", imagery)):
            if values:
                metadata = ET.SubElement(band, "Metadata", **({} if domain is None else {"domain": domain}))
                for key, value in values.items():
                    ET.SubElement(metadata, "MDI", key=key).text = value
    ET.indent(root, space="  ")
    path = pam_path(store, array)
    write_atomic(path, ET.tostring(root, encoding="unicode").encode() + b"\n")
    return path
