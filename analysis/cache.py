"""One cache for everything the pipeline derives once and reuses: look-up tables, their refocus
normalisations and work buffers, the depth fit's lens index.

Whoever processes a batch owns one :class:`Cache` (the ``plenodust`` command, a service worker, a
notebook) and hands it to the functions that can use it; nothing in :mod:`analysis` keeps a cache
of its own. One policy for all entries: least recently used first out, within a byte budget.

Example::

    from analysis.cache import Cache
    cache = Cache(directory=Path("~/.cache/plenodust").expanduser())
    for exposure in exposures:
        result = process(exposure, calibration, params, cache=cache)
"""

from __future__ import annotations

import contextlib
import glob
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

T = TypeVar("T")

#: Default budget: two full-size F01 look-up tables (refocus and depth fit, ~150 MB), a handful of
#: alpha ranges' normalisations (~20 MB each) and the work buffers, with room to spare.
DEFAULT_MAX_BYTES = 512 * 1024 * 1024


def nbytes_of(value: Any) -> int:
    """Memory held by a cached value: arrays, objects with an ``nbytes`` attribute, and tuples,
    lists or dicts of those (anything else counts as nothing)."""
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, (tuple, list)):
        return sum(nbytes_of(v) for v in value)
    if isinstance(value, dict):
        return sum(nbytes_of(v) for v in value.values())
    size = getattr(value, "nbytes", None)
    return int(size) if isinstance(size, (int, np.integer)) else 0


class Cache:
    """A least-recently-used store of derived data within a byte budget.

    Parameters
    ----------
    max_bytes : int
        Entries are dropped, least recently used first, while the entries held exceed this
        (an entry larger than the whole budget is still returned, just not kept).
    directory : Path, optional
        Where derived data that is worth keeping across processes (look-up tables) is written
        and read back; None keeps everything in memory only.

    Keys are tuples whose first item names the kind of entry (``("table", ...)``,
    ``("normalisation", table_uid, ...)``); :meth:`entries` lists those of one kind and owner.
    Safe to share between threads (one lock around the bookkeeping; values are built outside it,
    so two threads may build the same value once each).
    """

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES, *, directory: Path | None = None) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self.directory = None if directory is None else Path(directory)
        self._entries: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._entries

    @property
    def nbytes(self) -> int:
        """Bytes held by the entries."""
        return self._bytes

    def get(self, key: Hashable, default: Any = None) -> Any:
        """The entry under ``key`` (now the most recently used), or ``default``."""
        with self._lock:
            item = self._entries.get(key)
            if item is None:
                return default
            self._entries.move_to_end(key)
            return item[0]

    def put(self, key: Hashable, value: T) -> T:
        """Keep ``value`` under ``key`` and return it; drops the least recently used entries
        that no longer fit the budget."""
        size = nbytes_of(value)
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            self._entries[key] = (value, size)
            self._bytes += size
            while self._bytes > self.max_bytes and self._entries:
                _, (_, dropped) = self._entries.popitem(last=False)
                self._bytes -= dropped
        return value

    def get_or_make(self, key: Hashable, make: Callable[[], T]) -> T:
        """The entry under ``key``, made by ``make()`` and kept when missing."""
        value = self.get(key, _MISSING)
        if value is _MISSING:
            value = self.put(key, make())
        return value

    def take(self, key: Hashable) -> Any:
        """Remove and return the entry (None if missing): for work buffers that one caller at a
        time may use, and puts back when done."""
        with self._lock:
            item = self._entries.pop(key, None)
            if item is None:
                return None
            self._bytes -= item[1]
            return item[0]

    def entries(self, kind: str, owner: Hashable) -> Iterator[tuple[tuple, Any]]:
        """``(key, value)`` of the entries whose key starts with ``(kind, owner)``, oldest first."""
        with self._lock:
            items = [(k, v) for k, (v, _) in self._entries.items()
                     if isinstance(k, tuple) and len(k) >= 2 and k[0] == kind and k[1] == owner]
        return iter(items)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self._bytes = 0


_MISSING = object()


def remove_older_versions(folder: Path, prefix: str, version: int) -> list[Path]:
    """Delete the cache files ``folder/<prefix><k>*.npz`` of format versions ``k`` below ``version``:
    an older plenodust wrote them and no newer one reads them (a look-up table is ~100 MB). Returns
    what was removed; files that cannot be removed are left."""
    removed = []
    for old in Path(folder).glob(f"{glob.escape(prefix)}*.npz"):
        match = re.match(re.escape(prefix) + r"(\d+)\.", old.name)
        if match and int(match.group(1)) < version:
            with contextlib.suppress(OSError):
                old.unlink()
                removed.append(old)
    return removed
