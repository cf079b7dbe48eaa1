"""What is wrong with an archive's catalog, one line per problem (``archive catalog validate``,
``archive verify``): the index (a cache of the Items: damaged, of another schema, or out of date)
and every flight the catalog cannot describe (an unreadable Item, a collection without an Item, an
Item whose collection store is gone). Reads only."""

from __future__ import annotations

from archive.catalog.index import index_problem, scan_catalog
from archive.catalog.root import ArchiveRoot


def catalog_problems(root: ArchiveRoot, items: bool = True) -> list[tuple[str, str]]:
    """(file, problem and fix) for each problem of ``root``'s catalog. ``items`` False leaves out
    unreadable Items (a caller that validates every Item file reports those itself)."""
    out: list[tuple[str, str]] = []
    problem = index_problem(root.index_path, root)
    if problem is not None and problem != "missing":
        out.append((str(root.index_path), f"the catalog index is {problem} (it is a cache of the Items: the next "
                                          "search rebuilds it, or run 'archive catalog rebuild')"))
    _, damaged, _, _ = scan_catalog(root)
    for d in damaged:
        if d.kind == "item" and not items:
            continue
        where = root.items / f"{d.id}.json" if d.kind in ("item", "no-store") else root.collections / f"{d.id}.zarr"
        out.append((str(where), f"{d.reason} ({d.fix})"))
    return out
