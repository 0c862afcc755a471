"""Free space on the data disk: checked before writing, so a full disk is refused cleanly.

Below ``margin_bytes`` free (``PLENODUST_MIN_FREE_BYTES``) the service is not ready, refuses
uploads with 507 and starts no job; a job that could not store its result for want of space
fails with ``waits_for = 'space'`` and runs again once space returns.
"""

from __future__ import annotations

import errno
import shutil
from dataclasses import dataclass
from pathlib import Path

# Errors that mean "no room": the disk is full, or the user's quota is.
_NO_ROOM = {errno.ENOSPC, errno.EDQUOT}


class NoSpace(Exception):
    """The data disk has too little free space for a write (answered as 507).

    Parameters
    ----------
    data_dir : Path
        The data folder.
    needed_bytes : int
        Free space the write needs, margin included.
    free_bytes : int
        Free space now.
    """

    def __init__(self, data_dir: Path, *, needed_bytes: int, free_bytes: int, what: str = "this write") -> None:
        self.data_dir = data_dir
        self.needed_bytes = needed_bytes
        self.free_bytes = free_bytes
        super().__init__(
            f"the data folder {data_dir} has {format_bytes(free_bytes)} free; {what} needs "
            f"{format_bytes(needed_bytes)} (the service keeps PLENODUST_MIN_FREE_BYTES free): free space "
            f"on that disk, lower PLENODUST_RAW_RETENTION, or move --data to a larger disk")


def format_bytes(count: int) -> str:
    """``count`` bytes for people: ``1.5 GB``."""
    value = float(count)
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(value) < 1000 or unit == "TB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1000
    return f"{value:.1f} TB"


def is_out_of_space(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) is an ``OSError`` for a full disk or quota."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, NoSpace) or (isinstance(exc, OSError) and exc.errno in _NO_ROOM):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


@dataclass(frozen=True)
class DiskGuard:
    """The free-space rule of one data folder.

    Attributes
    ----------
    data_dir : Path
    margin_bytes : int
        Free space the service keeps; writes that would go below it are refused.
    """

    data_dir: Path
    margin_bytes: int

    def free_bytes(self) -> int:
        """Free space on the data folder's disk for this user (``statvfs`` ``f_bavail``)."""
        return int(shutil.disk_usage(self.data_dir).free)

    def ok(self) -> bool:
        """Whether at least the margin is free."""
        return self.free_bytes() >= self.margin_bytes

    def require(self, size_bytes: int, *, what: str = "this write") -> None:
        """Raise :class:`NoSpace` unless ``size_bytes`` fit with the margin left free."""
        free = self.free_bytes()
        needed = int(size_bytes) + self.margin_bytes
        if free < needed:
            raise NoSpace(self.data_dir, needed_bytes=needed, free_bytes=free, what=what)

    def status(self) -> dict:
        """For ``/readyz`` (:class:`service.models.DiskSpace`)."""
        free = self.free_bytes()
        return {"data_dir": str(self.data_dir), "free_bytes": free, "margin_bytes": self.margin_bytes,
                "ok": free >= self.margin_bytes}
