"""A least-recently-used cache bounded by the bytes of what it holds (thread-safe).

The viewer keeps three of them: encoded tiles (PNG bytes), cube bands (DN arrays read from the
store) and flight geometries (meshes). Each entry is charged the size its caller gives; the oldest
entries go when the total passes ``max_bytes``. An entry larger than the whole limit is not kept.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

__all__ = ["ByteLRU", "CacheStats"]


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
