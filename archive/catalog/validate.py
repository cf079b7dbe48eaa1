"""Offline validation of STAC objects against the schemas vendored in ``catalogs/schemas/``.

An Item, Catalog or Collection (or an ItemCollection, feature by feature) is checked against the
core schema of its ``type`` (STAC 1.1.0) and against the schema of every URL in its
``stac_extensions``. Schema URLs resolve through a :class:`referencing.Registry` built from the
vendored files (``catalogs/schemas/README.md`` lists them and where they come from); a URL that is
not vendored is an error naming it, never a download.

pystac can use the same schemas: :func:`archive.catalog.pystac_validator.use_with_pystac` installs
a validator so that ``item.validate()`` and ``catalog.validate_all()`` work offline (that module
needs pystac; this one only jsonschema).
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from archive.errors import FormatError

#: The STAC version whose core schemas are vendored (and that the archive writes).
STAC_VERSION = "1.1.0"
_CORE = f"https://schemas.stacspec.org/v{STAC_VERSION}"
#: Core schema URL of each STAC object type.
CORE_SCHEMAS = {
    "Feature": f"{_CORE}/item-spec/json-schema/item.json",
    "Catalog": f"{_CORE}/catalog-spec/json-schema/catalog.json",
    "Collection": f"{_CORE}/collection-spec/json-schema/collection.json",
}
_EXTENSIONS = "https://stac-extensions.github.io"
_SPEC_FOLDER = {"catalog": "catalog-spec", "collection": "collection-spec"}


def _schema_folder():
    return importlib.resources.files("archive.catalogs") / "schemas"


def _vendored() -> Iterator[tuple[str, Any]]:
    """(URL, file) of every vendored schema, the URL derived from the file's place:
    ``stac-spec/v<V>/<name>.json``, ``geojson/<Name>.json``, ``extensions/<ext>/v<V>/schema.json``."""
    root = _schema_folder()
    for version in (root / "stac-spec").iterdir():
        for f in version.iterdir():
            if f.name.endswith(".json"):
                stem = f.name[:-len(".json")]
                yield f"https://schemas.stacspec.org/{version.name}/{_SPEC_FOLDER.get(stem, 'item-spec')}/" \
                      f"json-schema/{f.name}", f
    for f in (root / "geojson").iterdir():
        if f.name.endswith(".json"):
            yield f"https://geojson.org/schema/{f.name}", f
    for ext in (root / "extensions").iterdir():
        if ext.is_dir():
            for version in ext.iterdir():
                f = version / "schema.json"
                if f.is_file():
                    yield f"{_EXTENSIONS}/{ext.name}/{version.name}/schema.json", f


@functools.cache
def vendored_schemas() -> dict[str, dict]:
    """Every vendored schema by its URL (no fragment)."""
    return {url: json.loads(f.read_text(encoding="utf-8")) for url, f in _vendored()}


class _NotVendored(LookupError):
    pass


def _refuse(uri: str):
    """The registry's fallback for a URL it does not hold: never fetch it."""
    from referencing.exceptions import NoSuchResource

    raise NoSuchResource(ref=uri)


@functools.cache
def schema_registry():
    """A :class:`referencing.Registry` of the vendored schemas that refuses any other URL (the
    JSON Schema meta-schemas are added by jsonschema itself, from its own package)."""
    from referencing import Registry, Resource
    from referencing.jsonschema import DRAFT7

    resources = [(url, Resource.from_contents(schema, default_specification=DRAFT7))
                 for url, schema in vendored_schemas().items()]
    return Registry(retrieve=_refuse).with_resources(resources)  # type: ignore[call-arg]


@functools.cache
def _validator(url: str):
    from jsonschema import Draft7Validator

    try:
        schema = vendored_schemas()[url.split("#")[0]]
    except KeyError:
        raise _NotVendored(url) from None
    return Draft7Validator(schema, registry=schema_registry(), format_checker=Draft7Validator.FORMAT_CHECKER)


def _read(obj_or_path: dict | str | os.PathLike) -> tuple[dict, str]:
    if isinstance(obj_or_path, dict):
        return obj_or_path, str(obj_or_path.get("id", "STAC object"))
    from archive import storage

    path = storage.location(obj_or_path) if storage.is_url(obj_or_path) else Path(obj_or_path)   # s3:// too
    try:
        obj = json.loads(path.read_text())
    except FileNotFoundError:
        from archive.errors import MissingInputError

        raise MissingInputError(path, "STAC file") from None
    except (OSError, ValueError) as exc:
        raise FormatError(path, f"unreadable STAC JSON: {exc}") from exc
    if not isinstance(obj, dict):
        raise FormatError(path, "a STAC object must be a JSON object")
    return obj, str(path)


def schema_urls(obj: dict, where: str = "STAC object") -> list[str]:
    """The schemas ``obj`` must satisfy: the core schema of its type, then its ``stac_extensions``.
    FormatError for an unknown type or a STAC version whose schemas are not vendored."""
    kind = obj.get("type")
    if kind not in CORE_SCHEMAS:
        raise FormatError(where, f"type {kind!r} is not a STAC Item, Catalog or Collection")
    version = obj.get("stac_version")
    if version != STAC_VERSION:
        raise FormatError(where, f"stac_version {version!r}: only the STAC {STAC_VERSION} schemas are vendored",
                          "rewrite it ('archive catalog rebuild --items' for an archive's Items)")
    extensions = obj.get("stac_extensions") or []
    if not isinstance(extensions, list):
        raise FormatError(where, "stac_extensions must be a list of schema URLs")
    return [CORE_SCHEMAS[kind], *(str(e) for e in extensions)]


def validation_errors(obj_or_path: dict | str | os.PathLike) -> list[str]:
    """Every way ``obj_or_path`` (a STAC dict or a JSON file) fails its schemas, one line each
    (``<schema URL>: <JSON path>: <message>``); empty when valid. An ItemCollection is checked
    feature by feature. Never touches the network."""
    obj, where = _read(obj_or_path)
    if obj.get("type") == "FeatureCollection":
        out = []
        for k, feature in enumerate(obj.get("features") or []):
            out += [f"features[{k}]: {e}" for e in validation_errors(feature)]
        return out
    try:
        urls = schema_urls(obj, where)
    except FormatError as exc:
        return [exc.problem]
    return [e for url in urls for e in errors_against(obj, url)]


def errors_against(obj: dict, url: str) -> list[str]:
    """How the STAC dict ``obj`` fails the one vendored schema ``url`` (lines as
    :func:`validation_errors`); a schema that is not vendored, or refers to one that is not, is an
    error line too (never fetched)."""
    from referencing.exceptions import Unresolvable

    # like pystac: through JSON and back, so that tuples count as arrays
    data = json.loads(json.dumps(obj))
    try:
        found = sorted(_validator(url).iter_errors(data), key=lambda e: list(e.absolute_path))
    except _NotVendored:
        return [f"{url}: schema not vendored in catalogs/schemas (not fetched: validation is offline)"]
    except Unresolvable as exc:
        return [f"{url}: refers to {exc}, which is not vendored (not fetched: validation is offline)"]
    return [f"{url}: {'/'.join(str(p) for p in e.absolute_path) or '(root)'}: {_short(e)}" for e in found]


def _short(error) -> str:
    """The most specific message of a jsonschema error: for a oneOf/anyOf, the deepest failure of
    its branches (a branch for another object type fails at the root, the one that matters deeper)."""
    leaves = [error]
    while any(e.context for e in leaves):
        leaves = [c for e in leaves for c in (e.context or [e])]
    error = max(leaves, key=lambda e: len(e.absolute_path))
    where = "/".join(str(p) for p in error.absolute_path)
    text = f"{where}: {error.message}" if where else error.message
    return text if len(text) <= 300 else text[:297] + "..."


def validate(obj_or_path: dict | str | os.PathLike) -> list[str]:
    """Validate a STAC Item, Catalog, Collection or ItemCollection (a dict, or the path of its JSON
    file) against the vendored schemas, offline. Returns the schema URLs it satisfies (core first,
    then extensions); FormatError listing every failure otherwise."""
    obj, where = _read(obj_or_path)
    errors = validation_errors(obj)
    if errors:
        shown = "; ".join(errors[:5]) + (f"; ... {len(errors) - 5} more" if len(errors) > 5 else "")
        raise FormatError(where, f"not valid STAC: {shown}")
    if obj.get("type") == "FeatureCollection":
        return sorted({u for f in obj.get("features") or [] for u in schema_urls(f)})
    return schema_urls(obj, where)
