"""Pure encoding and decoding of the Lytro F01 protocol; no I/O.

Byte layouts follow ``shared/docs/lytro-f01.md``: section 2 (bulk-only transport over USB
and the vendor SCSI commands) and section 3 (the same commands framed for Wi-Fi). Every
function here takes and returns bytes or plain records, so tests can hold them against the
documented layouts and the simulated camera can reuse them.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from datetime import datetime, timezone

from driver.errors import ProtocolError

# Device identity (section 2.1).
VENDOR_ID = 0x24CF
PRODUCT_ID = 0x00A1
INTERFACE = 0
EP_OUT = 0x02
EP_IN = 0x82

# Bulk-only transport wrappers (USB Mass Storage Class, Bulk-Only Transport 1.0).
CBW_SIGNATURE = b"USBC"
CSW_SIGNATURE = b"USBS"
CBW_STRUCT = struct.Struct("<4sIIBBB16s")
CSW_STRUCT = struct.Struct("<4sIIB")
CBW_LENGTH = CBW_STRUCT.size  # 31
CSW_LENGTH = CSW_STRUCT.size  # 13
CBW_FLAG_IN = 0x80
CSW_PASSED = 0
CSW_FAILED = 1
CSW_PHASE_ERROR = 2
# Class-specific control requests (BOT 1.0 section 3).
BOT_RESET_REQUEST_TYPE = 0x21  # host-to-device, class, interface
BOT_RESET_REQUEST = 0xFF
GET_MAX_LUN_REQUEST_TYPE = 0xA1
GET_MAX_LUN_REQUEST = 0xFE

# Opcode classes and sub-commands (section 2.3).
OP_CONTROL = 0xC0
OP_LOAD = 0xC2
OP_DOWNLOAD = 0xC4
OP_QUERY = 0xC6
LOAD_HARDWARE_INFO = 0x00
LOAD_FILE = 0x01
LOAD_PICTURE_LIST = 0x02
QUERY_LENGTH = 0x00
QUERY_TIME = 0x03
QUERY_BATTERY = 0x06
CONTROL_TAKE_PICTURE = 0x00
# Download byte 2: lyli and pyly send 1 over USB; Kucera's LCL sends 0 over Wi-Fi (section 6).
DOWNLOAD_SUBCODE_USB = 1
DOWNLOAD_SUBCODE_KUCERA = 0

HARDWARE_INFO_STRUCT = struct.Struct("<256s128s128s128si")
HARDWARE_INFO_LENGTH = HARDWARE_INFO_STRUCT.size  # 644
LENGTH_REPLY = 4
TIME_REPLY = 14
BATTERY_REPLY = 4

PICTURE_LIST_HEADER = struct.Struct("<iii")
PICTURE_ENTRY_STRUCT = struct.Struct("<8s8sii16sif48s28si")
PICTURE_ENTRY_LENGTH = PICTURE_ENTRY_STRUCT.size  # 128

# Wi-Fi framing (section 3).
WIFI_MAGIC = 0xFAAA55AF
WIFI_HEADER_STRUCT = struct.Struct("<III16s")
WIFI_HEADER_LENGTH = WIFI_HEADER_STRUCT.size  # 28
WIFI_FLAG_READ = 0x1  # length is the reply-buffer size; no payload follows
WIFI_FLAG_RESPONSE = 0x2
WIFI_COMMAND_PORT = 5678
WIFI_CALLBACK_PORT = 5677
NEW_PICTURE_CALLBACK = "[NewPictureAvailable]"

PICTURE_ROOT = "I:\\DCIM"
CALIBRATION_ROOT = "C:\\T1CALIB"
# lyli looks for calibration files MOD_0000 .. MOD_0061.
CALIBRATION_INDICES = range(62)

_ROTATION_DEGREES = {1: 0, 8: 90, 3: 180, 6: 270}


# -- bulk-only transport -------------------------------------------------------------


@dataclass(frozen=True)
class CommandBlockWrapper:
    """A decoded 31-byte command block wrapper (CBW)."""

    tag: int
    data_length: int
    direction_in: bool
    lun: int
    cdb: bytes  # the significant bytes (``bCBWCBLength`` of them)


@dataclass(frozen=True)
class CommandStatusWrapper:
    """A decoded 13-byte command status wrapper (CSW)."""

    tag: int
    residue: int
    status: int


def encode_cbw(cdb: bytes, *, tag: int, data_length: int, direction_in: bool, lun: int = 0) -> bytes:
    """Wrap a CDB in a 31-byte command block wrapper.

    Parameters
    ----------
    cdb : bytes
        1 to 16 command bytes; ``bCBWCBLength`` is set to their count and the field is
        zero-padded to 16 bytes.
    tag : int
        Echoed by the device in the status wrapper.
    data_length : int
        Bytes expected in the data phase (0 for none).
    direction_in : bool
        True when the data phase goes device to host.

    Examples
    --------
    >>> encode_cbw(bytes(16), tag=1, data_length=0, direction_in=False)[:8]
    b'USBC\\x01\\x00\\x00\\x00'
    """
    if not 1 <= len(cdb) <= 16:
        raise ValueError(f"a CDB has 1 to 16 bytes, got {len(cdb)}")
    flags = CBW_FLAG_IN if direction_in else 0
    return CBW_STRUCT.pack(CBW_SIGNATURE, tag & 0xFFFFFFFF, data_length, flags, lun, len(cdb), cdb)


def decode_cbw(data: bytes) -> CommandBlockWrapper:
    """Parse a command block wrapper; raise :class:`ProtocolError` if it is not valid."""
    if len(data) != CBW_LENGTH:
        raise ProtocolError(f"a command block wrapper has {CBW_LENGTH} bytes, got {len(data)}")
    signature, tag, length, flags, lun, cb_length, cdb = CBW_STRUCT.unpack(bytes(data))
    if signature != CBW_SIGNATURE:
        raise ProtocolError(f"command block wrapper signature is {signature!r}, expected {CBW_SIGNATURE!r}")
    if not 1 <= cb_length <= 16 or flags & 0x7F or lun > 15:
        raise ProtocolError(f"command block wrapper has reserved bits set (flags {flags:#x}, "
                            f"LUN {lun}, CB length {cb_length})")
    return CommandBlockWrapper(tag, length, bool(flags & CBW_FLAG_IN), lun, cdb[:cb_length])


def encode_csw(*, tag: int, residue: int, status: int) -> bytes:
    """Build a 13-byte command status wrapper."""
    return CSW_STRUCT.pack(CSW_SIGNATURE, tag & 0xFFFFFFFF, residue, status)


def decode_csw(data: bytes) -> CommandStatusWrapper:
    """Parse a 13-byte command status wrapper, checking its length and signature.

    The tag, residue and status are checked against the command by the transport.
    """
    if len(data) != CSW_LENGTH:
        raise ProtocolError(f"a command status wrapper has {CSW_LENGTH} bytes, got {len(data)}")
    signature, tag, residue, status = CSW_STRUCT.unpack(bytes(data))
    if signature != CSW_SIGNATURE:
        raise ProtocolError(f"command status wrapper signature is {signature!r}, expected {CSW_SIGNATURE!r}")
    return CommandStatusWrapper(tag, residue, status)


# -- command descriptor blocks -------------------------------------------------------


def encode_cdb(opcode: int, sub: int = 0, offset: int | None = None, *, length: int = 16) -> bytes:
    """Build a Lytro CDB: opcode, 0x00, sub-command, optional LE uint32 offset, zeros.

    ``length`` is 16 (pyly) or 12 (lyli); both are reported to work.
    """
    if length not in (12, 16):
        raise ValueError(f"CDB length must be 12 or 16, got {length}")
    cdb = bytearray(length)
    cdb[0] = opcode
    cdb[2] = sub
    if offset is not None:
        struct.pack_into("<I", cdb, 3, offset)
    return bytes(cdb)


def cdb_test_unit_ready(*, length: int = 16) -> bytes:
    """TEST UNIT READY: all zeros, no data phase."""
    return bytes(length)


def cdb_load_hardware_info(*, length: int = 16) -> bytes:
    """Load hardware info (``C2 00 00``); then query its length and download 644 bytes."""
    return encode_cdb(OP_LOAD, LOAD_HARDWARE_INFO, length=length)


def cdb_load_file(*, length: int = 16) -> bytes:
    """Load file by path; the NUL-terminated path follows as an OUT data phase."""
    return encode_cdb(OP_LOAD, LOAD_FILE, length=length)


def cdb_load_picture_list(*, length: int = 16) -> bytes:
    """Load the picture list (``C2 00 02``); then query its length and download it."""
    return encode_cdb(OP_LOAD, LOAD_PICTURE_LIST, length=length)


def cdb_query_length(*, length: int = 16) -> bytes:
    """Query the length of the loaded content (``C6 00 00``): 4 bytes, uint32 LE, 0 = not found."""
    return encode_cdb(OP_QUERY, QUERY_LENGTH, length=length)


def cdb_query_time(*, length: int = 16) -> bytes:
    """Query the camera's clock (``C6 00 03``): 14 bytes."""
    return encode_cdb(OP_QUERY, QUERY_TIME, length=length)


def cdb_query_battery(*, length: int = 16) -> bytes:
    """Query the battery level (``C6 00 06``): float32 LE percent."""
    return encode_cdb(OP_QUERY, QUERY_BATTERY, length=length)


def cdb_take_picture(*, length: int = 16) -> bytes:
    """Take a picture (``C0 00 00``); documented for Wi-Fi only."""
    return encode_cdb(OP_CONTROL, CONTROL_TAKE_PICTURE, length=length)


def cdb_download(offset: int, *, subcode: int = DOWNLOAD_SUBCODE_USB, length: int = 16) -> bytes:
    """Download (read) loaded content from ``offset``: ``C4 00 <subcode> <LE32 offset>``.

    Examples
    --------
    >>> cdb_download(0x10000)[:7].hex()
    'c4000100000100'
    """
    if not 0 <= offset <= 0xFFFFFFFF:
        raise ValueError(f"download offset {offset} does not fit in 32 bits")
    return encode_cdb(OP_DOWNLOAD, subcode, offset, length=length)


def decode_cdb(cdb: bytes) -> tuple[int, int, int]:
    """Split a CDB into (opcode, sub-command, LE32 offset at bytes 3..6)."""
    cdb = bytes(cdb).ljust(16, b"\0")
    return cdb[0], cdb[2], struct.unpack_from("<I", cdb, 3)[0]


def encode_path(path: str) -> bytes:
    """A camera path as sent after load-file: ASCII with a terminating NUL."""
    try:
        return path.encode("ascii") + b"\0"
    except UnicodeEncodeError:
        raise ValueError(f"camera paths are ASCII, got {path!r}") from None


def decode_path(data: bytes) -> str:
    return bytes(data).split(b"\0", 1)[0].decode("ascii", errors="replace")


# -- replies ---------------------------------------------------------------------------


@dataclass(frozen=True)
class HardwareInfo:
    """The 644-byte hardware-info reply: four NUL-padded strings and an unknown int32."""

    manufacturer: str
    serial: str
    build: str
    software: str
    unknown: int = 0


def _cstr(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")


def decode_hardware_info(data: bytes) -> HardwareInfo:
    """Parse the 644-byte hardware info (strings at 0x000, 0x100, 0x180, 0x200; int32 at 0x280)."""
    if len(data) < HARDWARE_INFO_LENGTH:
        raise ProtocolError(f"hardware info has {HARDWARE_INFO_LENGTH} bytes, got {len(data)}")
    manufacturer, serial, build, software, unknown = HARDWARE_INFO_STRUCT.unpack_from(bytes(data))
    return HardwareInfo(_cstr(manufacturer), _cstr(serial), _cstr(build), _cstr(software), unknown)


def encode_hardware_info(info: HardwareInfo) -> bytes:
    """The 644-byte hardware info reply (for the simulated camera)."""
    return HARDWARE_INFO_STRUCT.pack(info.manufacturer.encode("ascii"), info.serial.encode("ascii"),
                                     info.build.encode("ascii"), info.software.encode("ascii"), info.unknown)


def decode_length(data: bytes) -> int:
    """The uint32 LE of a length query."""
    if len(data) < LENGTH_REPLY:
        raise ProtocolError(f"the length reply has {LENGTH_REPLY} bytes, got {len(data)}")
    return struct.unpack_from("<I", bytes(data))[0]


def encode_length(value: int) -> bytes:
    return struct.pack("<I", value)


def decode_battery(data: bytes) -> float:
    """The float32 LE percent of a battery query."""
    if len(data) < BATTERY_REPLY:
        raise ProtocolError(f"the battery reply has {BATTERY_REPLY} bytes, got {len(data)}")
    return struct.unpack_from("<f", bytes(data))[0]


def encode_battery(percent: float) -> bytes:
    return struct.pack("<f", percent)


def decode_time(data: bytes) -> datetime:
    """Seven LE uint16 (year, month, day, hour, minute, second, millisecond), UTC."""
    if len(data) < TIME_REPLY:
        raise ProtocolError(f"the time reply has {TIME_REPLY} bytes, got {len(data)}")
    y, mo, d, h, mi, s, ms = struct.unpack_from("<7H", bytes(data))
    try:
        return datetime(y, mo, d, h, mi, s, ms * 1000, tzinfo=timezone.utc)
    except ValueError as exc:
        raise ProtocolError(f"the camera sent an invalid time {(y, mo, d, h, mi, s, ms)}: {exc}") from None


def encode_time(when: datetime) -> bytes:
    when = when.astimezone(timezone.utc)
    return struct.pack("<7H", when.year, when.month, when.day, when.hour, when.minute, when.second,
                       when.microsecond // 1000)


# -- picture list ----------------------------------------------------------------------


@dataclass(frozen=True)
class Picture:
    """One entry of the camera's picture list (128 bytes, section 2.6).

    ``path`` is the on-camera path of the ``.RAW``; :meth:`path_for` gives the sibling
    files. ``taken`` is the capture time in UTC.
    """

    folder_name: str
    file_prefix: str
    folder_number: int
    file_number: int
    id: str
    taken: datetime
    starred: bool = False
    last_lambda: float = 0.0
    rotation: int = 1  # EXIF code
    unknown: bytes = bytes(16)

    @property
    def name(self) -> str:
        """File stem on the camera, e.g. ``IMG_0001``."""
        return f"{self.file_prefix}{self.file_number:04d}"

    @property
    def folder(self) -> str:
        """On-camera folder, e.g. ``I:\\DCIM\\100PHOTO``."""
        return f"{PICTURE_ROOT}\\{self.folder_number:03d}{self.folder_name}"

    @property
    def path(self) -> str:
        """On-camera path of the raw sensor file."""
        return self.path_for("RAW")

    def path_for(self, extension: str) -> str:
        """On-camera path of this picture's ``RAW``, ``TXT`` or ``128`` file."""
        return f"{self.folder}\\{self.name}.{extension}"

    @property
    def rotation_degrees(self) -> int:
        """Counter-clockwise rotation; 0 for an unknown EXIF code."""
        return _ROTATION_DEGREES.get(self.rotation, 0)


def format_taken(when: datetime) -> str:
    """ISO 8601 as on the camera: ``YYYY-MM-DDTHH:MM:SS.sssZ``."""
    when = when.astimezone(timezone.utc)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def _parse_taken(text: str) -> datetime:
    try:
        when = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ProtocolError(f"picture date {text!r} is not ISO 8601") from None
    return when if when.tzinfo else when.replace(tzinfo=timezone.utc)


def decode_picture_entry(data: bytes) -> Picture:
    """Parse one 128-byte picture-list entry."""
    if len(data) != PICTURE_ENTRY_LENGTH:
        raise ProtocolError(f"a picture-list entry has {PICTURE_ENTRY_LENGTH} bytes, got {len(data)}")
    (folder_name, prefix, folder_no, file_no, unknown, starred, lam, pid, taken,
     rotation) = PICTURE_ENTRY_STRUCT.unpack(bytes(data))
    return Picture(folder_name=_cstr(folder_name), file_prefix=_cstr(prefix), folder_number=folder_no,
                   file_number=file_no, id=_cstr(pid), taken=_parse_taken(_cstr(taken)),
                   starred=bool(starred), last_lambda=lam, rotation=rotation, unknown=unknown)


def encode_picture_entry(picture: Picture) -> bytes:
    """One 128-byte picture-list entry (for the simulated camera)."""
    return PICTURE_ENTRY_STRUCT.pack(
        picture.folder_name.encode("ascii"), picture.file_prefix.encode("ascii"), picture.folder_number,
        picture.file_number, picture.unknown, int(picture.starred), picture.last_lambda,
        picture.id.encode("ascii"), format_taken(picture.taken).encode("ascii"), picture.rotation)


def decode_picture_list(data: bytes) -> list[Picture]:
    """Parse the picture list: header (1, entry length, N, N x {index, offset}), then entries.

    Entries start at ``12 + 8 N`` and run to the end, each of the header's entry length
    (the first 128 bytes of each are the documented fields).
    """
    data = bytes(data)
    if len(data) < PICTURE_LIST_HEADER.size:
        raise ProtocolError(f"the picture list is {len(data)} bytes, shorter than its 12-byte header")
    version, entry_length, n_defs = PICTURE_LIST_HEADER.unpack_from(data)
    if version != 1:
        raise ProtocolError(f"picture list version is {version}, expected 1")
    if entry_length < PICTURE_ENTRY_LENGTH or n_defs < 0:
        raise ProtocolError(f"picture list header is inconsistent (entry length {entry_length}, "
                            f"{n_defs} record definitions)")
    start = PICTURE_LIST_HEADER.size + 8 * n_defs
    body = len(data) - start
    if body < 0 or body % entry_length:
        raise ProtocolError(f"picture list body of {body} bytes is not a whole number of "
                            f"{entry_length}-byte entries")
    return [decode_picture_entry(data[o:o + PICTURE_ENTRY_LENGTH]) for o in range(start, len(data), entry_length)]


def encode_picture_list(pictures: list[Picture], *, record_definitions: tuple[tuple[int, int], ...] = ()) -> bytes:
    """A picture list with 128-byte entries; the meaning of record definitions is unknown."""
    out = bytearray(PICTURE_LIST_HEADER.pack(1, PICTURE_ENTRY_LENGTH, len(record_definitions)))
    for index, offset in record_definitions:
        out += struct.pack("<ii", index, offset)
    for picture in pictures:
        out += encode_picture_entry(picture)
    return bytes(out)


def picture_id(raw: bytes) -> str:
    """The picture id this project's simulated camera gives a picture: ``sha1-`` + SHA-1 of its ``.RAW`` bytes.

    What a real F01 hashes for its ids is not documented, so the driver checks downloads
    against this rule only when asked to (``verify_id``).
    """
    return "sha1-" + hashlib.sha1(raw).hexdigest()


def calibration_path(index: int, extension: str) -> str:
    """``C:\\T1CALIB\\MOD_nnnn.<extension>``."""
    return f"{CALIBRATION_ROOT}\\MOD_{index:04d}.{extension}"


def basename(camera_path: str) -> str:
    """Last component of a camera path (``I:\\DCIM\\100PHOTO\\IMG_0001.RAW`` -> ``IMG_0001.RAW``)."""
    return camera_path.rsplit("\\", 1)[-1]


# -- Wi-Fi framing ---------------------------------------------------------------------


@dataclass(frozen=True)
class WifiHeader:
    """The 28-byte Wi-Fi message header: magic, length, flags, command (16 bytes)."""

    length: int
    flags: int
    command: bytes


def encode_wifi_header(command: bytes, *, length: int, flags: int) -> bytes:
    """Frame a 16-byte command (same as the USB CDB) for TCP port 5678."""
    if len(command) > 16:
        raise ValueError(f"a Wi-Fi command has at most 16 bytes, got {len(command)}")
    return WIFI_HEADER_STRUCT.pack(WIFI_MAGIC, length, flags, bytes(command).ljust(16, b"\0"))


def decode_wifi_header(data: bytes) -> WifiHeader:
    """Parse a 28-byte Wi-Fi header, checking the magic."""
    if len(data) != WIFI_HEADER_LENGTH:
        raise ProtocolError(f"a Wi-Fi header has {WIFI_HEADER_LENGTH} bytes, got {len(data)}")
    magic, length, flags, command = WIFI_HEADER_STRUCT.unpack(bytes(data))
    if magic != WIFI_MAGIC:
        raise ProtocolError(f"Wi-Fi magic is {magic:#010x}, expected {WIFI_MAGIC:#010x}")
    return WifiHeader(length, flags, command)


def parse_callback(message: bytes) -> tuple[str, str]:
    """Split a callback message (``[Name] argument``, NUL-terminated) into name and argument."""
    text = bytes(message).rstrip(b"\0").decode("ascii", errors="replace").strip()
    name, _, arg = text.partition(" ")
    return name, arg.strip()
