"""A simulated Lytro F01: its file system and its command set, shared by the USB and Wi-Fi fakes.

The camera's file system is a folder, for instance one written by ``plenodust simulate``:

=================================  ==========================================
folder                             camera path
=================================  ==========================================
``IMG_nnnn.RAW`` / ``.TXT`` / ``.128``  ``I:\\DCIM\\100PHOTO\\IMG_nnnn.*``
``calibration/MOD_nnnn.RAW`` / ``.TXT``  ``C:\\T1CALIB\\MOD_nnnn.*``
=================================  ==========================================

Other files are ignored. The picture list is rebuilt from the ``IMG_*.RAW`` files present
at each list command, so a demo "takes" a picture by dropping files into the folder
(:meth:`CameraFolder.add_picture` does it atomically). A picture's id is
:func:`driver.protocol.picture_id` of its ``.RAW`` bytes; its date is the file's mtime.

The transport layers (:mod:`driver.simulated_usb`, :mod:`driver.simulated_wifi`) wrap
:class:`SimulatedCamera` and add the faults of :class:`FaultPlan`.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Literal

from driver import protocol as p

FaultKind = Literal["stall", "timeout", "short", "bad_csw_signature", "bad_csw_tag", "phase_error",
                    "gone", "reset"]
FAULT_KINDS: tuple[str, ...] = FaultKind.__args__  # type: ignore[attr-defined]

_PICTURE_RE = re.compile(r"^(?P<prefix>IMG_)(?P<number>\d{4})\.RAW$", re.IGNORECASE)
_PICTURE_FOLDER = re.compile(r"^I:\\DCIM\\(?P<number>\d{3})(?P<name>[A-Z]+)\\(?P<file>[^\\]+)$", re.IGNORECASE)
_CALIB_FOLDER = re.compile(r"^C:\\T1CALIB\\(?P<file>MOD_\d{4}\.(RAW|TXT))$", re.IGNORECASE)
_SIDE_EXTENSIONS = ("RAW", "TXT", "128")


def _camera_serial(node: object, parent: str = "") -> str | None:
    # The first "serialNumber" inside a "camera" object, wherever the JSON puts it.
    if isinstance(node, dict):
        value = node.get("serialNumber")
        if parent == "camera" and isinstance(value, str) and value:
            return value
        children = node.items()
    elif isinstance(node, list):
        children = ((parent, v) for v in node)
    else:
        return None
    for key, child in children:
        found = _camera_serial(child, key)
        if found:
            return found
    return None


def _atomic_write(path: Path, data: bytes) -> None:
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", delete=False) as tmp:
        tmp.write(data)
    os.replace(tmp.name, path)


class CameraFolder:
    """A folder seen as the camera's file system (layout in the module docstring).

    Parameters
    ----------
    root : path
        The folder; it need not hold any picture yet.
    folder_number, folder_name : int, str
        On-camera folder of the pictures (``100``, ``PHOTO`` gives ``I:\\DCIM\\100PHOTO``).
    """

    def __init__(self, root: str | os.PathLike, *, folder_number: int = 100, folder_name: str = "PHOTO") -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"simulated camera folder {self.root} does not exist; create it "
                                    "or fill it with `plenodust simulate --out DIR`")
        self.folder_number = folder_number
        self.folder_name = folder_name
        # Picture ids by file and (mtime, size): each .RAW is hashed once, not at every list.
        self._ids: dict[Path, tuple[tuple[int, int], str]] = {}
        # The last file read, so that loading it again (a resumed download) costs no disk read.
        self._last: tuple[Path, tuple[int, int], bytes] | None = None
        self._lock = threading.Lock()

    def read(self, camera_path: str) -> bytes | None:
        """Bytes of the file at ``camera_path``, or None if the camera has no such file."""
        local = self.resolve(camera_path)
        if local is None:
            return None
        try:
            st = local.stat()
            key = (st.st_mtime_ns, st.st_size)
            last = self._last
            if last is not None and last[0] == local and last[1] == key:
                return last[2]
            data = local.read_bytes()
        except FileNotFoundError:  # removed since resolved
            return None
        self._last = (local, key, data)
        return data

    def resolve(self, camera_path: str) -> Path | None:
        """The local file that backs ``camera_path``, or None."""
        m = _PICTURE_FOLDER.match(camera_path)
        if m and int(m["number"]) == self.folder_number and m["name"].upper() == self.folder_name:
            name = m["file"]
            stem, _, ext = name.rpartition(".")
            if stem.upper().startswith("IMG_") and ext.upper() in _SIDE_EXTENSIONS:
                return self._find(self.root, name)
            return None
        m = _CALIB_FOLDER.match(camera_path)
        if m:
            return self._find(self.root / "calibration", m["file"])
        return None

    def pictures(self) -> list[p.Picture]:
        """The picture list as the camera would report it now, oldest number first."""
        result = []
        for local in sorted(self.root.iterdir()):
            m = _PICTURE_RE.match(local.name)
            if not m or not local.is_file():
                continue
            try:
                st = local.stat()
                picture_id = self._picture_id(local, st)
            except FileNotFoundError:  # removed while listing
                continue
            result.append(p.Picture(
                folder_name=self.folder_name, file_prefix=m["prefix"].upper(), folder_number=self.folder_number,
                file_number=int(m["number"]), id=picture_id,
                taken=datetime.fromtimestamp(st.st_mtime, tz=timezone.utc)))
        result.sort(key=lambda pic: pic.file_number)
        return result

    def serial(self) -> str | None:
        """The camera serial its white images carry (``camera.serialNumber`` in a ``MOD_nnnn.TXT``),
        or None: a camera reports the serial its own files name."""
        folder = self.root / "calibration"
        if not folder.is_dir():
            return None
        for txt in sorted(folder.glob("MOD_*.TXT")):
            try:
                found = _camera_serial(json.loads(txt.read_bytes()))
            except (OSError, ValueError):
                continue
            if found:
                return found
        return None

    def remove_oldest(self, *, keep: int) -> list[str]:
        """Delete all but the newest ``keep`` pictures (a card has room for so many); returns
        the stems removed. The ``.RAW`` goes first, so a listed picture is always whole."""
        stems = [f"IMG_{pic.file_number:04d}" for pic in self.pictures()]
        gone = stems[:max(0, len(stems) - keep)]
        for stem in gone:
            for ext in ("RAW", *[e for e in _SIDE_EXTENSIONS if e != "RAW"]):
                (self.root / f"{stem}.{ext}").unlink(missing_ok=True)
        return gone

    def next_number(self) -> int:
        numbers = [int(m["number"]) for f in self.root.iterdir() if (m := _PICTURE_RE.match(f.name))]
        return max(numbers, default=0) + 1

    def add_picture(self, raw: bytes, txt: bytes, thumbnail: bytes | None = None, *,
                    number: int | None = None) -> str:
        """Write a new picture (``.TXT`` and ``.128`` first, ``.RAW`` last, each atomically).

        Returns the file stem, e.g. ``IMG_0003``. The ``.RAW`` appears last because its
        presence is what puts the picture in the list.
        """
        stem = f"IMG_{number if number is not None else self.next_number():04d}"
        _atomic_write(self.root / f"{stem}.TXT", txt)
        if thumbnail is not None:
            _atomic_write(self.root / f"{stem}.128", thumbnail)
        _atomic_write(self.root / f"{stem}.RAW", raw)
        return stem

    @staticmethod
    def _find(folder: Path, name: str) -> Path | None:
        exact = folder / name
        if exact.is_file():
            return exact
        if folder.is_dir():  # the camera's names are upper case; the folder's need not be
            for candidate in folder.iterdir():
                if candidate.name.upper() == name.upper() and candidate.is_file():
                    return candidate
        return None

    def _picture_id(self, local: Path, st: os.stat_result) -> str:
        key = (st.st_mtime_ns, st.st_size)
        with self._lock:
            hit = self._ids.get(local)
        if hit and hit[0] == key:
            return hit[1]
        picture_id = p.picture_id(local.read_bytes())
        with self._lock:
            self._ids[local] = (key, picture_id)
        return picture_id


@dataclass
class Fault:
    """One injected fault.

    Attributes
    ----------
    kind : str
        One of :data:`FAULT_KINDS`.
    first : int
        Index (counting every download command the camera has served, from 0) of the
        first download command it hits.
    count : int or None
        How many download commands in a row it hits; None for all from ``first`` on.
    """

    kind: str
    first: int
    count: int | None = 1

    def hits(self, download_index: int) -> bool:
        if download_index < self.first:
            return False
        return self.count is None or download_index < self.first + self.count


@dataclass
class FaultPlan:
    """Faults to inject into download commands (``C4``), where a real camera misbehaves.

    ============  =========================================================================
    kind          what the simulated camera does on a hit download
    ============  =========================================================================
    stall         stalls the bulk-IN pipe in the data phase; after clear halt its status
                  wrapper reports "failed" (USB only)
    timeout       does not answer the data phase (the transfer times out at once)
    short         sends only half of the requested bytes, rounded up (the residue says so)
    bad_csw_signature  status wrapper starts with ``USBX`` (USB only)
    bad_csw_tag   status wrapper carries the wrong tag (USB only)
    phase_error   status wrapper reports a phase error (USB only)
    gone          disappears: every later transfer fails with "no device"; it no longer
                  enumerates (over Wi-Fi: closes the connection and stops listening)
    reset         reboots: the transfer fails, the loaded file is forgotten, and the next
                  TEST UNIT READY commands report "not ready" a few times
    ============  =========================================================================
    """

    faults: list[Fault] = field(default_factory=list)
    downloads_served: int = 0

    def add(self, kind: str, *, after: int = 0, count: int | None = 1) -> Fault:
        """Inject ``kind`` into the download command ``after`` commands from now."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; choose one of {', '.join(FAULT_KINDS)}")
        fault = Fault(kind, self.downloads_served + after, count)
        self.faults.append(fault)
        return fault

    def next_download(self) -> set[str]:
        """Count one download command and return the kinds that hit it."""
        index = self.downloads_served
        self.downloads_served += 1
        return {f.kind for f in self.faults if f.hits(index)}


@dataclass
class CameraIdentity:
    """What the simulated camera reports about itself."""

    manufacturer: str = "Lytro, Inc."
    serial: str = "A000000001"
    build: str = "v1.0a208"
    software: str = "v1.2.2"
    battery_percent: float = 87.5


Shutter = Callable[[CameraFolder], object]


class SimulatedCamera:
    """The command set of an F01 over a :class:`CameraFolder`, independent of transport.

    Parameters
    ----------
    folder : CameraFolder or path
        The camera's file system.
    identity : CameraIdentity, optional
        Hardware info and battery level; by default the serial is that of the folder's white
        images (:meth:`CameraFolder.serial`), else ``A000000001``.
    download_subcode : {1, 0}
        The byte 2 that download commands must carry (1 as lyli and pyly send).
    not_ready_after_reset : int
        TEST UNIT READY commands answered "not ready" after a reset.
    shutter : callable, optional
        Called with the folder on a take-picture command (``C0 00 00``); it should add a
        picture, e.g. with :meth:`CameraFolder.add_picture`. Without it the command fails.
    clock : callable, optional
        Returns the camera's time (default: now, UTC).
    """

    def __init__(self, folder: CameraFolder | str | os.PathLike, *, identity: CameraIdentity | None = None,
                 download_subcode: int = p.DOWNLOAD_SUBCODE_USB, not_ready_after_reset: int = 2,
                 shutter: Shutter | None = None, clock: Callable[[], datetime] | None = None) -> None:
        self.folder = folder if isinstance(folder, CameraFolder) else CameraFolder(folder)
        # A camera reports the serial its own files carry (its white images'), as a real one does.
        self.identity = identity or CameraIdentity(serial=self.folder.serial() or CameraIdentity.serial)
        self.download_subcode = download_subcode
        self.not_ready_after_reset = not_ready_after_reset
        self.shutter = shutter
        self.clock = clock or (lambda: datetime.now(timezone.utc))
        self.loaded: bytes | None = None
        self.loaded_path: str | None = None
        self._not_ready = 0
        self.commands: list[bytes] = []  # every CDB served, for tests

    @classmethod
    def of(cls, folder: CameraFolder | str | os.PathLike | None, camera: SimulatedCamera | None,
           **settings) -> SimulatedCamera:
        """``camera`` if given, else a new camera over ``folder`` (what the simulated transports take)."""
        if camera is not None:
            return camera
        if folder is None:
            raise ValueError("give the simulated camera a folder or a SimulatedCamera")
        return cls(folder, **settings)

    def reboot(self, *, not_ready: int | None = None) -> None:
        """Forget the loaded content and be "not ready" for a while, as after a crash.

        ``not_ready`` TEST UNIT READY commands fail (default: ``not_ready_after_reset``).
        """
        self.loaded = None
        self.loaded_path = None
        self._not_ready = self.not_ready_after_reset if not_ready is None else not_ready

    def handle(self, cdb: bytes, *, data_out: bytes | None = None,
               data_in_length: int = 0) -> tuple[bool, bytes | memoryview]:
        """Serve one command.

        Returns
        -------
        (ok, reply) : (bool, bytes or memoryview)
            ``ok`` False means the command failed; ``reply`` is at most ``data_in_length``
            bytes (a view into the loaded file for downloads, so large reads copy once).
        """
        cdb = bytes(cdb)
        self.commands.append(cdb)
        opcode, sub, offset = p.decode_cdb(cdb)
        if not any(cdb):  # TEST UNIT READY
            if self._not_ready:
                self._not_ready -= 1
                return False, b""
            return True, b""
        if self._not_ready:
            return False, b""
        reply: bytes | memoryview = b""
        if opcode == p.OP_LOAD:
            if sub == p.LOAD_HARDWARE_INFO:
                i = self.identity
                self._load("hardware info", p.encode_hardware_info(
                    p.HardwareInfo(i.manufacturer, i.serial, i.build, i.software, 0)))
            elif sub == p.LOAD_FILE:
                if not data_out:
                    return False, b""
                path = p.decode_path(data_out)
                # An absent file loads as empty: the length query then answers 0.
                self._load(path, self.folder.read(path) or b"")
            elif sub == p.LOAD_PICTURE_LIST:
                self._load("picture list", p.encode_picture_list(self.folder.pictures()))
            else:
                return False, b""
        elif opcode == p.OP_QUERY:
            if sub == p.QUERY_LENGTH:
                reply = p.encode_length(len(self.loaded) if self.loaded is not None else 0)
            elif sub == p.QUERY_TIME:
                reply = p.encode_time(self.clock())
            elif sub == p.QUERY_BATTERY:
                reply = p.encode_battery(self.identity.battery_percent)
            else:
                return False, b""
        elif opcode == p.OP_DOWNLOAD:
            if sub != self.download_subcode or self.loaded is None or offset > len(self.loaded):
                return False, b""
            reply = memoryview(self.loaded)[offset:offset + data_in_length]
        elif opcode == p.OP_CONTROL and sub == p.CONTROL_TAKE_PICTURE:
            if self.shutter is None:
                return False, b""
            self.shutter(self.folder)
        else:
            return False, b""
        return True, reply[:data_in_length]

    def _load(self, path: str, data: bytes) -> None:
        self.loaded_path = path
        self.loaded = data
