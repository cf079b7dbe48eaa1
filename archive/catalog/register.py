"""Rendered outputs as assets of the flights they came from (``archive catalog add OUT.json``).

A rendered output's Item (``<out>.json``, :mod:`archive.catalog.product`) names its sources in
``archive:recipe.sources``; each source that is a collection of the archive gets an asset
``output-<output id>`` on its Item: the output's data file (href relative to the flight's Item),
its media type, roles ``data`` and ``archive:output``, and ``archive:item``, the output's own Item.
Rewriting a flight's Item (re-ingest, ``archive catalog rebuild --items``) keeps these assets
(:func:`carry_outputs`). The index is unchanged (outputs are not searched by themselves): the STAC API
serves the assets with the flight's Item.
"""

from __future__ import annotations

import os
from pathlib import Path

from archive.catalog.index import read_item_file
from archive.catalog.root import ArchiveRoot
from archive.catalog.stac import write_item
from archive.errors import InputError, MissingInputError

OUTPUT_ROLE = "archive:output"


def _rel(target: Path, start: Path) -> str:
    return Path(os.path.relpath(target, start)).as_posix()


def output_asset(product: dict, product_path: Path, flight_item_dir: Path) -> tuple[str, dict]:
    """(asset key, asset) linking a flight's Item to a rendered output, hrefs relative to
    ``flight_item_dir``."""
    data = (product.get("assets") or {}).get("data")
    if not isinstance(data, dict) or not data.get("href"):
        raise InputError(product_path, "the Item has no 'data' asset", "give the <out>.json that archive render wrote")
    href = str(data["href"])
    target = Path(href) if os.path.isabs(href) else (product_path.absolute().parent / href)
    asset = {"href": _rel(os.path.normpath(target), flight_item_dir.absolute()),
             "title": f"rendered: {data.get('title') or product.get('id')}",
             "roles": ["data", OUTPUT_ROLE],
             "archive:item": _rel(product_path.absolute(), flight_item_dir.absolute())}
    if data.get("type"):
        asset["type"] = data["type"]
    return f"output-{product['id']}", asset


def register_output(root: ArchiveRoot, product_path: str | os.PathLike) -> list[str]:
    """Add the output described by ``product_path`` (an ``<out>.json``) to the Items of its
    source collections; returns their ids. InputError when none of its sources is a collection
    of this archive."""
    from archive.catalog.tree import locked

    product_path = Path(product_path)
    if not product_path.is_file():
        raise MissingInputError(product_path, "output Item (<out>.json)")
    product = read_item_file(product_path)
    recipe = (product.get("properties") or {}).get("archive:recipe") or {}
    sources = [str(s) for s in recipe.get("sources") or []]
    targets = [s for s in sources if _is_collection(root, s)]
    if not targets:
        raise InputError(product_path, f"none of its sources ({', '.join(sources) or 'none recorded'}) is a "
                                       f"collection of {root.path}",
                         "render from the archive's collection ids (archive render ID --archive ARCHIVE)")
    with locked(root):
        for cid in targets:
            path = root.item_path(cid)
            item = read_item_file(path)
            key, asset = output_asset(product, product_path, path.parent)
            item.setdefault("assets", {})[key] = asset
            write_item(path, item)
    return targets


def carry_outputs(old: dict | None, new: dict) -> dict:
    """``new`` with the output assets of ``old`` (an Item being rewritten) added back."""
    for key, asset in ((old or {}).get("assets") or {}).items():
        if OUTPUT_ROLE in (asset.get("roles") or []) and key not in new.setdefault("assets", {}):
            new["assets"][key] = asset
    return new


def _is_collection(root: ArchiveRoot, source: str) -> bool:
    try:
        return root.item_path(source).is_file()
    except InputError:  # not an id (a directory path)
        return False
