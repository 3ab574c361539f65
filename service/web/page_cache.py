"""A small in-memory cache of what the pages draw from stored data that never changes: a flight's figures (its
normalized flight is content-addressed: the blob's sha names it) and a finished evaluation's report page (its
report and stored estimates are written once).  Drawing them from a long flight costs seconds of CPU; after the
first view a page is served from here.

Bounded in bytes (least recently used entries leave first), per server process; a restart empties it.  Requests
for the same entry at once wait for the one that draws it, so three first views cost one drawing.
"""
from __future__ import annotations

import sys
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

T = TypeVar("T")
MAX_BYTES = 64 << 20     # all entries together (a long flight's figures are a few hundred kB after decimation)
MAX_ENTRY_BYTES = 16 << 20


def _size(value: Any) -> int:
    """Bytes of a cached value: the text it holds (str, bytes, or a dict / tuple of them)."""
    if isinstance(value, (str, bytes)):
        return len(value)
    if isinstance(value, dict):
        return sum(_size(v) for v in value.values()) + 64
    if isinstance(value, (tuple, list)):
        return sum(_size(v) for v in value) + 64
    return sys.getsizeof(value)


class PageCache:
    """Least-recently-used values by key, at most ``max_bytes`` in all.

    Parameters
    ----------
    max_bytes : int
        Bound of the cached values' sizes together, bytes.
    """

    def __init__(self, max_bytes: int = MAX_BYTES) -> None:
        self.max_bytes = max_bytes
        self._entries: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._drawing: dict[Hashable, threading.Lock] = {}

    def get(self, key: Hashable, compute: Callable[[], T], keep: Callable[[T], bool] = lambda _v: True) -> T:
        """The value cached under ``key``, else ``compute()`` (once, whoever else asks meanwhile), cached when
        ``keep(value)`` says so and it is not larger than MAX_ENTRY_BYTES."""
        found = self._lookup(key)
        if found is not None:
            return found[0]
        with self._lock:
            drawing = self._drawing.setdefault(key, threading.Lock())
        with drawing:
            found = self._lookup(key)
            if found is not None:
                return found[0]
            value = compute()
            if keep(value):
                self._store(key, value)
        with self._lock:
            self._drawing.pop(key, None)
        return value

    def _lookup(self, key: Hashable) -> tuple[Any] | None:
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return (entry[0],)

    def _store(self, key: Hashable, value: Any) -> None:
        size = _size(value)
        if size > MAX_ENTRY_BYTES:
            return
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            self._entries[key] = (value, size)
            self._bytes += size
            while self._bytes > self.max_bytes and self._entries:
                _, (_, dropped) = self._entries.popitem(last=False)
                self._bytes -= dropped

    def clear(self) -> None:
        """Forget every entry."""
        with self._lock:
            self._entries.clear()
            self._bytes = 0

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)


pages = PageCache()   # the server process's one cache
