"""The Lytro F01 as an object: commands, retries, resumable downloads, atomic files.

:class:`Camera` speaks the command layer of ``lytro-f01.md`` section 2.3-2.6 over any
transport with the :class:`Transport` interface (USB bulk-only in :mod:`driver.bot`, TCP in
:mod:`driver.wifi`). Retries live here, not in the transports: a command that times out,
gets a bad status wrapper or a stall is retried after the transport's recovery; a download
that fails midway is loaded again and resumed from its offset; a camera that went away
raises :class:`CameraGone` at once. Files are written only when complete (temporary file,
fsync, ``os.replace``), so a failed pull leaves nothing behind.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import threading
import time as _time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Callable, Iterator, Protocol, TypeVar

from driver import protocol as p
from driver.errors import (CameraError, CameraFileNotFound, CameraGone, CameraTimeout, CommandFailed,
                           IntegrityError, ProtocolError)

log = logging.getLogger(__name__)

T = TypeVar("T")
Progress = Callable[[str, int, int], None]
"""Called as ``progress(camera_path, bytes_done, bytes_total)`` after each chunk."""

_TRANSIENT = (CameraTimeout, ProtocolError, CommandFailed)


class Transport(Protocol):
    """What :class:`Camera` needs from a transport (USB bulk-only or Wi-Fi)."""

    cdb_length: int
    """12 or 16: the length of the command blocks this transport sends."""

    def execute(self, cdb: bytes, *, data_out: bytes | None = None, data_in_length: int = 0) -> memoryview:
        """Run one command and return the bytes received (valid until the next command)."""

    def recover(self) -> None:
        """Bring the link back to a known state after an error."""

    def close(self) -> None:
        """Release the device or connection."""


@dataclass(frozen=True)
class CameraSettings:
    """How :class:`Camera` runs commands.

    Attributes
    ----------
    chunk_size : int
        Bytes per download command (lyli uses 64 KiB; pyly 32 KiB over SCSI generic).
    retries : int
        Extra attempts for a command, or per failure of a download, before giving up.
    ready_timeout_s : float
        How long :meth:`Camera.wait_ready` waits for TEST UNIT READY to pass.
    ready_poll_s : float
        Pause between TEST UNIT READY attempts.
    verify_id : bool
        Check that SHA-1 of a pulled ``.RAW`` equals the picture id (the rule of
        :func:`driver.protocol.picture_id`; true for the simulated camera, unverified for a
        real F01, hence off by default).
    download_subcode : {1, 0}
        Byte 2 of download commands: 1 as lyli and pyly send over USB, 0 as Kucera's
        library sends over Wi-Fi (``lytro-f01.md`` section 6).
    """

    chunk_size: int = 64 * 1024
    retries: int = 3
    ready_timeout_s: float = 10.0
    ready_poll_s: float = 0.05
    verify_id: bool = False
    download_subcode: int = p.DOWNLOAD_SUBCODE_USB

    def __post_init__(self) -> None:
        if not 512 <= self.chunk_size <= 0x200000:
            raise ValueError(f"chunk_size must be 512 B .. 2 MiB (the camera's buffer), got {self.chunk_size}")
        if self.retries < 0:
            raise ValueError(f"retries must be >= 0, got {self.retries}")
        if self.download_subcode not in (p.DOWNLOAD_SUBCODE_USB, p.DOWNLOAD_SUBCODE_KUCERA):
            raise ValueError(f"download_subcode must be 1 (lyli, pyly) or 0 (Kucera), got {self.download_subcode}")


class Camera:
    """A connected Lytro F01.

    Get one from :func:`driver.open_usb`, :func:`driver.open_wifi` or
    :func:`driver.open_simulated`; use it as a context manager or call :meth:`close`.
    Methods are safe to call from several threads (one command runs at a time).
    """

    def __init__(self, transport: Transport, settings: CameraSettings | None = None) -> None:
        self.transport = transport
        self.settings = settings or CameraSettings()
        self._lock = threading.RLock()
        # Set by transports that hear of new pictures (Wi-Fi callbacks) to wake watch().
        self.new_picture = threading.Event()
        # Whether take_picture() is known to work on this connection: set by open_wifi (the
        # documented case) and by open_simulated with a shutter; over USB it is unknown
        # (lytro-f01.md section 6), so it stays False there.
        self.can_take_pictures = False

    # -- lifetime ------------------------------------------------------------------

    def __enter__(self) -> Camera:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the camera (and give it back to the kernel driver over USB)."""
        with self._lock:
            self.transport.close()

    # -- simple commands -----------------------------------------------------------

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Send TEST UNIT READY until it passes.

        Raises
        ------
        CameraTimeout
            If the camera is not ready within ``timeout_s`` (default: the setting).
        """
        timeout_s = self.settings.ready_timeout_s if timeout_s is None else timeout_s
        deadline = _time.monotonic() + timeout_s
        with self._lock:
            while True:
                try:
                    self.transport.execute(p.cdb_test_unit_ready(length=self.transport.cdb_length))
                    return
                except CommandFailed:
                    pass
                except (CameraTimeout, ProtocolError) as exc:
                    log.info("not ready yet: %s", exc)
                    self.transport.recover()
                if _time.monotonic() >= deadline:
                    raise CameraTimeout(f"the camera was not ready within {timeout_s:g} s; wait until it "
                                        "has finished starting up (or raise ready_timeout_s)")
                _time.sleep(self.settings.ready_poll_s)

    def info(self) -> p.HardwareInfo:
        """Manufacturer, serial number, build and software version."""
        data = self._download(lambda: self._run(p.OP_LOAD, p.LOAD_HARDWARE_INFO), "hardware info")
        return p.decode_hardware_info(data)

    def pictures(self) -> list[p.Picture]:
        """The camera's picture list, as :class:`driver.protocol.Picture` records."""
        data = self._download(lambda: self._run(p.OP_LOAD, p.LOAD_PICTURE_LIST), "picture list", allow_empty=True)
        # A camera without pictures may answer length 0 rather than an empty list.
        return p.decode_picture_list(data) if data else []

    def battery(self) -> float:
        """Battery level in percent."""
        return p.decode_battery(self._query(p.QUERY_BATTERY, p.BATTERY_REPLY))

    def time(self) -> datetime:
        """The camera's clock (UTC; milliseconds are not reported by the camera)."""
        return p.decode_time(self._query(p.QUERY_TIME, p.TIME_REPLY))

    def take_picture(self) -> None:
        """Press the shutter (``C0 00 00``).

        Documented for Wi-Fi only; whether a real F01 accepts it over USB is unknown
        (``lytro-f01.md`` section 6).
        """
        with self._lock:
            self._retrying(lambda: self._run(p.OP_CONTROL, p.CONTROL_TAKE_PICTURE), "taking a picture")

    # -- files ---------------------------------------------------------------------

    def read_file(self, path: str, *, progress: Progress | None = None) -> bytes:
        """Download one file by its camera path (e.g. ``I:\\DCIM\\100PHOTO\\IMG_0001.TXT``).

        Raises
        ------
        CameraFileNotFound
            If the camera has no such file.
        """
        return bytes(self._fetch(path, progress=progress))

    def pull(self, picture: p.Picture, dest_dir: str | os.PathLike, *,
             progress: Progress | None = None) -> list[Path]:
        """Copy a picture's ``.RAW``, ``.TXT`` and (if present) ``.128`` into ``dest_dir``.

        All files are downloaded before any is written, and each is written atomically,
        so a failure leaves no file of this picture behind.

        Returns
        -------
        list of Path
            The files written, named as on the camera (``IMG_0001.RAW`` ...).

        Raises
        ------
        IntegrityError
            If ``verify_id`` is set and the ``.RAW`` does not hash to the picture id.
        """
        dest = Path(dest_dir)
        dest.mkdir(parents=True, exist_ok=True)
        with self._lock:
            files: list[tuple[str, bytearray]] = []
            for ext in ("RAW", "TXT", "128"):
                path = picture.path_for(ext)
                try:
                    # Kept as the download buffer: a 16 MB copy less on the way to disk.
                    files.append((p.basename(path), self._fetch(path, progress=progress)))
                except CameraFileNotFound:
                    if ext != "128":
                        raise
            if self.settings.verify_id:
                found = "sha1-" + hashlib.sha1(files[0][1]).hexdigest()
                if found != picture.id:
                    raise IntegrityError(f"{picture.path} hashes to {found}, not its id {picture.id}; pull it "
                                         "again, or pass verify_id=False if this camera ids pictures otherwise")
        return [write_atomic(dest / name, data) for name, data in files]

    def pull_calibration(self, dest_dir: str | os.PathLike, *, progress: Progress | None = None) -> list[Path]:
        """Copy the white images ``C:\\T1CALIB\\MOD_nnnn.RAW/.TXT`` (nnnn = 0000..0061) into ``dest_dir``.

        Absent indices are skipped, as lyli does. Each file is written once complete.
        """
        dest = Path(dest_dir)
        dest.mkdir(parents=True, exist_ok=True)
        written = []
        with self._lock:
            for index in p.CALIBRATION_INDICES:
                for ext in ("TXT", "RAW"):
                    path = p.calibration_path(index, ext)
                    try:
                        data = self._fetch(path, progress=progress)
                    except CameraFileNotFound:
                        continue
                    written.append(write_atomic(dest / p.basename(path), data))
        return written

    def watch(self, poll_s: float = 2.0, stop: threading.Event | None = None, *,
              include_existing: bool = False) -> Iterator[p.Picture]:
        """Yield each new picture as it appears, by polling the picture list.

        Parameters
        ----------
        poll_s : float
            Seconds between polls (a Wi-Fi new-picture callback cuts the wait short).
        stop : threading.Event, optional
            Set it to end the iteration; without it, iterate until the caller stops.
        include_existing : bool
            Also yield the pictures already on the camera, first.
        """
        stop = stop or threading.Event()
        seen = set() if include_existing else {(pic.path, pic.id) for pic in self.pictures()}
        while not stop.is_set():
            self.new_picture.clear()
            for pic in self.pictures():
                if (pic.path, pic.id) not in seen:
                    seen.add((pic.path, pic.id))
                    yield pic
            if stop.is_set():
                break
            # Wake on a callback, a stop request, or after poll_s, whichever comes first.
            deadline = _time.monotonic() + poll_s
            while not stop.is_set() and not self.new_picture.is_set():
                remaining = deadline - _time.monotonic()
                if remaining <= 0:
                    break
                self.new_picture.wait(min(remaining, 0.05))

    # -- internals -----------------------------------------------------------------

    def _fetch(self, path: str, *, progress: Progress | None = None) -> bytearray:
        payload = p.encode_path(path)
        return self._download(lambda: self._run(p.OP_LOAD, p.LOAD_FILE, data_out=payload), path,
                              progress=progress)

    def _run(self, opcode: int, sub: int = 0, *, data_out: bytes | None = None, data_in_length: int = 0) -> memoryview:
        cdb = p.encode_cdb(opcode, sub, length=self.transport.cdb_length)
        return self.transport.execute(cdb, data_out=data_out,
                                      data_in_length=data_in_length)

    def _query(self, sub: int, length: int) -> bytes:
        with self._lock:
            return self._retrying(lambda: bytes(self._run(p.OP_QUERY, sub, data_in_length=length)),
                                  f"query {sub:#04x}")

    def _retrying(self, action: Callable[[], T], doing: str) -> T:
        attempts = self.settings.retries + 1
        for attempt in range(1, attempts + 1):
            try:
                return action()
            except _TRANSIENT as exc:
                if attempt == attempts:
                    raise type(exc)(f"{doing} failed {attempts} times; last error: {exc}") from exc
                log.warning("%s failed (%s); recovering, attempt %d of %d", doing, exc, attempt + 1, attempts)
                self._recover()
        raise AssertionError("unreachable")

    def _recover(self) -> None:
        try:
            self.transport.recover()
            self.wait_ready()
        except CameraGone:
            raise
        except CameraError as exc:  # the next attempt will tell
            log.warning("recovery incomplete: %s", exc)

    def _download(self, load: Callable[[], object], what: str, *, progress: Progress | None = None,
                  allow_empty: bool = False) -> bytearray:
        """Load content, query its length, then read it chunk by chunk, resuming after failures."""
        chunk = self.settings.chunk_size
        subcode = self.settings.download_subcode

        def load_and_size() -> int:
            load()
            return p.decode_length(self._run(p.OP_QUERY, p.QUERY_LENGTH, data_in_length=p.LENGTH_REPLY))

        with self._lock:
            size = self._retrying(load_and_size, f"loading {what}")
            if size == 0:
                if allow_empty:
                    return bytearray()
                raise CameraFileNotFound(f"the camera has no {what} (it reports length 0); "
                                         "check the path with `plenodust camera list`")
            out = bytearray(size)
            view = memoryview(out)
            offset = 0
            failures = 0
            while offset < size:
                want = min(chunk, size - offset)
                try:
                    got = self.transport.execute(
                        p.cdb_download(offset, subcode=subcode, length=self.transport.cdb_length),
                        data_in_length=want)
                    n = len(got)
                    if n == 0 or n > want:
                        raise ProtocolError(f"the camera sent {n} bytes for a {want}-byte read at offset {offset}")
                    view[offset:offset + n] = got
                except _TRANSIENT as exc:
                    failures += 1
                    if failures > self.settings.retries:
                        raise type(exc)(f"downloading {what} failed at byte {offset} of {size} "
                                        f"{failures} times in a row; last error: {exc}") from exc
                    log.warning("download of %s failed at byte %d (%s); resuming", what, offset, exc)
                    self._recover()
                    # A camera that restarted has forgotten what was loaded: load it again.
                    again = self._retrying(load_and_size, f"reloading {what}")
                    if again != size:
                        raise IntegrityError(f"{what} changed size during the download ({size} -> {again} "
                                             "bytes); pull it again") from exc
                    continue
                offset += n
                failures = 0
                if progress is not None:
                    progress(what, offset, size)
            return out


def write_atomic(path: Path, data: bytes | bytearray | memoryview) -> Path:
    """Write ``data`` to ``path`` so that ``path`` holds either nothing new or all of it.

    A temporary file in the same folder is written, fsynced and renamed over ``path``.
    """
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return path
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)
    return path
