"""A pystac validator that uses the vendored schemas (:mod:`archive.catalog.validate`), offline.

Install it with :func:`use_with_pystac` (or ``pystac.validation.set_validator(OfflineSTACValidator())``).
This module needs pystac (a test dependency); nothing else in the package imports it.
"""

from __future__ import annotations

from typing import Any

import pystac.validation
from pystac.errors import STACValidationError
from pystac.stac_object import STACObjectType
from pystac.validation.stac_validator import STACValidator

from archive.catalog.validate import CORE_SCHEMAS, STAC_VERSION, errors_against

_TYPES = {STACObjectType.ITEM: "Feature", STACObjectType.CATALOG: "Catalog",
          STACObjectType.COLLECTION: "Collection"}


class OfflineSTACValidator(STACValidator):
    """Validates core objects and extensions against ``catalogs/schemas/`` only; a schema that is
    not vendored is a :class:`pystac.errors.STACValidationError` naming it, never a download."""

    def _check(self, stac_dict: dict[str, Any], url: str, href: str | None) -> str:
        errors = errors_against(stac_dict, url)
        if errors:
            where = f" at {href}" if href else ""
            raise STACValidationError(f"Validation failed for {stac_dict.get('id')!r}{where} against {url}: "
                                      + "; ".join(errors[:5]), source=errors)
        return url

    def validate_core(self, stac_dict: dict[str, Any], stac_object_type: STACObjectType, stac_version: str,
                      href: str | None = None) -> str:
        if stac_version != STAC_VERSION:
            raise STACValidationError(f"STAC {stac_version}: only the {STAC_VERSION} schemas are vendored "
                                      f"({href or stac_dict.get('id')})")
        try:
            kind = _TYPES[stac_object_type]
        except KeyError:
            raise STACValidationError(f"no vendored schema for a {stac_object_type}") from None
        return self._check(stac_dict, CORE_SCHEMAS[kind], href)

    def validate_extension(self, stac_dict: dict[str, Any], stac_object_type: STACObjectType, stac_version: str,
                           extension_id: str, href: str | None = None) -> str:
        return self._check(stac_dict, extension_id, href)


def use_with_pystac() -> OfflineSTACValidator:
    """Make pystac validate with the vendored schemas (``pystac.validation.set_validator``), so
    that ``Item.validate()``, ``Catalog.validate_all()`` ... never fetch a schema. Returns the
    validator installed."""
    validator = OfflineSTACValidator()
    pystac.validation.set_validator(validator)
    return validator
