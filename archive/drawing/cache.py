"""A least-recently-used cache bounded by the bytes of what it holds (thread-safe), and
:func:`held_bytes`, what an object's arrays weigh.

The viewer keeps four of them: tiles (PNG bytes, band-value planes), band planes (and the ingest
previews), lookups, and the opened flights (their sources, poses and meshes, charged
:func:`held_bytes` after each job). Each entry is charged the size its caller gives; the oldest
entries go when the total passes ``max_bytes``. An entry larger than the whole limit is not kept.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

__all__ = ["ByteLRU", "CacheStats", "held_bytes"]


@dataclass(frozen=True)
class CacheStats:
    """entries, bytes held, limit (bytes), hits, misses, evictions."""

    entries: int
    bytes: int
    limit: int
    hits: int
    misses: int
    evictions: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class ByteLRU:
    """LRU mapping of hashable keys to values, at most ``max_bytes`` bytes in all (by the sizes
    given to :meth:`put`)."""

    def __init__(self, max_bytes: int):
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._hits = self._misses = self._evictions = 0

    def get(self, key: Hashable, default=None):
        """The value of ``key`` (now the most recently used), else ``default``."""
        with self._lock:
            found = self._items.get(key)
            if found is None:
                self._misses += 1
                return default
            self._items.move_to_end(key)
            self._hits += 1
            return found[0]

    def put(self, key: Hashable, value, nbytes: int) -> None:
        """Keep ``value`` under ``key``, charged ``nbytes``; evicts the least recently used
        entries beyond the limit (a value larger than the limit is not kept)."""
        nbytes = max(int(nbytes), 0)
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            if nbytes > self.max_bytes:
                return
            self._items[key] = (value, nbytes)
            self._bytes += nbytes
            while self._bytes > self.max_bytes and self._items:
                _, (_, size) = self._items.popitem(last=False)
                self._bytes -= size
                self._evictions += 1

    def get_or_make(self, key: Hashable, make: Callable[[], tuple[Any, int]]):
        """The value of ``key``, made by ``make() -> (value, nbytes)`` and kept when missing.
        (Not atomic: two threads may both make it; the viewer's band workers make distinct keys.)"""
        sentinel = object()
        value = self.get(key, sentinel)
        if value is sentinel:
            value, nbytes = make()
            self.put(key, value, nbytes)
        return value

    def pop_oldest(self) -> None:
        """Forget the least recently used entry (counted as an eviction); nothing when empty."""
        with self._lock:
            if self._items:
                _, (_, size) = self._items.popitem(last=False)
                self._bytes -= size
                self._evictions += 1

    def __contains__(self, key: Hashable) -> bool:
        """Whether ``key`` is held (neither a use nor a hit or miss)."""
        with self._lock:
            return key in self._items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0

    def stats(self) -> CacheStats:
        with self._lock:
            return CacheStats(len(self._items), self._bytes, self.max_bytes, self._hits, self._misses,
                              self._evictions)


def held_bytes(*roots, depth: int = 5) -> int:
    """Bytes of the numpy arrays reachable from ``roots`` through the attributes of this package's
    objects, dicts, lists, tuples and sets, ``depth`` levels deep; each array counted once (a view
    by its base), a scipy ``Rotation`` as its quaternions. What an opened flight holds beyond the
    Python objects themselves (its sources' per-line arrays, poses, meshes)."""
    import numpy as np

    seen: set[int] = set()
    total = 0
    stack = [(r, depth) for r in roots]
    while stack:
        obj, left = stack.pop()
        if obj is None or isinstance(obj, (str, bytes, int, float, bool)) or id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            if base is obj or id(base) not in seen:
                seen.add(id(base))
                total += base.nbytes
            continue
        if hasattr(obj, "as_quat") and hasattr(obj, "single"):   # scipy Rotation
            total += 32 * (1 if obj.single else len(obj))
            continue
        if left <= 0:
            continue
        if isinstance(obj, dict):
            children = list(obj.values())
        elif isinstance(obj, (list, tuple, set, frozenset)):
            children = list(obj)
        elif type(obj).__module__.startswith("archive.") and hasattr(obj, "__dict__"):
            children = list(vars(obj).values())
        elif type(obj).__module__.startswith("archive.") and hasattr(obj, "__slots__"):
            children = [getattr(obj, n, None) for n in obj.__slots__]
        else:
            continue
        stack.extend((c, left - 1) for c in children)
    return total
