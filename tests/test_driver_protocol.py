"""Wire bytes of the driver against the layouts in shared/docs/lytro-f01.md (sections 2 and 3).

Expected bytes are written out by hand from the document, never produced by the encoder
under test, so the driver and the simulated camera cannot agree on a mistake.
"""

from __future__ import annotations

import struct
from datetime import datetime, timezone

import pytest

from driver import protocol as p
from driver.errors import ProtocolError

PATH = "I:\\DCIM\\100PHOTO\\IMG_0001.RAW"  # 29 characters


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


# -- bulk-only transport wrappers (section 2.1: '<4sIIBBB16s', 'USBC', 13-byte 'USBS') ------


def test_cbw_test_unit_ready_is_31_bytes_of_the_documented_layout():
    cbw = p.encode_cbw(p.cdb_test_unit_ready(), tag=1, data_length=0, direction_in=False)
    assert cbw == h("55534243 01000000 00000000 00 00 10") + bytes(16)
    assert len(cbw) == 31


def test_cbw_load_file_is_an_out_command_of_path_length_plus_nul():
    cbw = p.encode_cbw(p.cdb_load_file(), tag=0x01020304, data_length=len(PATH) + 1, direction_in=False)
    assert cbw == h("55534243 04030201 1e000000 00 00 10 c20001") + bytes(13)
    assert p.encode_path(PATH) == PATH.encode("ascii") + b"\x00"


def test_cbw_download_sets_the_in_flag_and_length():
    cbw = p.encode_cbw(p.cdb_download(0x10000), tag=7, data_length=65536, direction_in=True)
    assert cbw == h("55534243 07000000 00000100 80 00 10 c4000100 000100") + bytes(9)


def test_cbw_with_lylis_12_byte_cdb_reports_length_12_and_pads_the_field():
    cbw = p.encode_cbw(p.cdb_query_length(length=12), tag=2, data_length=4, direction_in=True)
    assert cbw == h("55534243 02000000 04000000 80 00 0c c60000") + bytes(13)


def test_cbw_decode_round_trip_and_rejections():
    raw = h("55534243 09000000 04000000 80 00 10 c60006") + bytes(13)
    cbw = p.decode_cbw(raw)
    assert (cbw.tag, cbw.data_length, cbw.direction_in, cbw.lun) == (9, 4, True, 0)
    assert cbw.cdb == h("c60006") + bytes(13)
    with pytest.raises(ProtocolError, match="signature"):
        p.decode_cbw(b"USBX" + raw[4:])
    with pytest.raises(ProtocolError, match="31 bytes"):
        p.decode_cbw(raw[:30])


def test_csw_layout_and_checks():
    raw = h("55534253 2a000000 10000000 01")
    csw = p.decode_csw(raw)
    assert (csw.tag, csw.residue, csw.status) == (42, 16, 1)
    assert p.encode_csw(tag=42, residue=16, status=1) == raw
    with pytest.raises(ProtocolError, match="signature"):
        p.decode_csw(h("55534258 2a000000 10000000 00"))
    with pytest.raises(ProtocolError, match="13 bytes"):
        p.decode_csw(raw[:12])


# -- CDBs (section 2.2 and the opcode table of 2.3) ----------------------------------------


@pytest.mark.parametrize("make, first_bytes", [
    (p.cdb_load_hardware_info, "c20000"),
    (p.cdb_load_file, "c20001"),
    (p.cdb_load_picture_list, "c20002"),
    (p.cdb_query_length, "c60000"),
    (p.cdb_query_time, "c60003"),
    (p.cdb_query_battery, "c60006"),
    (p.cdb_take_picture, "c00000"),
])
def test_command_cdbs(make, first_bytes):
    assert make() == h(first_bytes) + bytes(13)
    assert make(length=12) == h(first_bytes) + bytes(9)


def test_battery_cdb_matches_pylys_struct():
    # pyly: getbat = struct.pack('<HB13x', 0xc6, 6)
    assert p.cdb_query_battery() == struct.pack("<HB13x", 0xC6, 6)


def test_download_cdb_byte2_is_1_and_offset_is_little_endian_at_bytes_3_to_6():
    # lyli: {0xc4, 00, 01, 00, 00, packet, ...} with offset = packet * 65536
    assert p.cdb_download(3 * 65536) == h("c4 00 01 00 00 03 00") + bytes(9)
    assert p.cdb_download(0x12345678) == h("c4 00 01 78 56 34 12") + bytes(9)
    # Kucera's Wi-Fi variant: byte 2 = 0
    assert p.cdb_download(0x20, subcode=0) == h("c4 00 00 20 00 00 00") + bytes(9)
    assert p.decode_cdb(h("c4 00 01 78 56 34 12") + bytes(9)) == (0xC4, 1, 0x12345678)
    with pytest.raises(ValueError):
        p.cdb_download(1 << 32)


# -- replies -------------------------------------------------------------------------------


def test_hardware_info_offsets():
    raw = bytearray(644)
    raw[0x000:0x000 + 11] = b"Lytro, Inc."
    raw[0x100:0x100 + 10] = b"A202110453"
    raw[0x180:0x180 + 8] = b"v1.0a208"
    raw[0x200:0x200 + 6] = b"v1.2.2"
    raw[0x280:0x284] = h("2a000000")
    info = p.decode_hardware_info(bytes(raw))
    assert info == p.HardwareInfo("Lytro, Inc.", "A202110453", "v1.0a208", "v1.2.2", 42)
    assert p.encode_hardware_info(info) == bytes(raw)
    with pytest.raises(ProtocolError, match="644"):
        p.decode_hardware_info(bytes(643))


def test_length_battery_and_time_replies():
    assert p.decode_length(h("00407600")) == 0x764000
    assert p.decode_battery(h("00004842")) == 50.0
    # 2012-04-12 14:10:55.000 UTC as seven little-endian uint16
    raw = h("dc07 0400 0c00 0e00 0a00 3700 0000")
    assert p.decode_time(raw) == datetime(2012, 4, 12, 14, 10, 55, tzinfo=timezone.utc)
    assert p.encode_time(datetime(2012, 4, 12, 14, 10, 55, tzinfo=timezone.utc)) == raw
    with pytest.raises(ProtocolError, match="invalid time"):
        p.decode_time(h("dc07 0d00 0c00 0e00 0a00 3700 0000"))  # month 13


# -- picture list (section 2.6) ------------------------------------------------------------

PICTURE_ID = "sha1-0360f825e6eed3c7c470fb79a755a54df07fae84"


def documented_entry(*, file_number: int, rotation: int) -> bytes:
    entry = bytearray(128)
    entry[0x00:0x05] = b"PHOTO"
    entry[0x08:0x0C] = b"IMG_"
    entry[0x10:0x14] = h("64000000")  # folder 100
    entry[0x14:0x18] = struct.pack("<i", file_number)
    entry[0x28:0x2C] = h("01000000")  # starred
    entry[0x2C:0x30] = h("0000803f")  # lambda 1.0
    entry[0x30:0x30 + 45] = PICTURE_ID.encode()
    entry[0x60:0x60 + 24] = b"2012-04-12T14:10:55.000Z"
    entry[0x7C:0x80] = struct.pack("<i", rotation)
    return bytes(entry)


def test_picture_list_with_record_definitions_is_parsed_from_offset_12_plus_8n():
    header = h("01000000 80000000 02000000") + h("00000000 00000000 01000000 80000000")
    data = header + documented_entry(file_number=1, rotation=6) + documented_entry(file_number=12, rotation=1)
    first, second = p.decode_picture_list(data)
    assert first.path == "I:\\DCIM\\100PHOTO\\IMG_0001.RAW"
    assert first.path_for("TXT") == "I:\\DCIM\\100PHOTO\\IMG_0001.TXT"
    assert first.name == "IMG_0001"
    assert first.id == PICTURE_ID
    assert first.taken == datetime(2012, 4, 12, 14, 10, 55, tzinfo=timezone.utc)
    assert first.starred and first.last_lambda == 1.0
    assert first.rotation_degrees == 270
    assert second.name == "IMG_0012" and second.rotation_degrees == 0


def test_picture_list_encoding_puts_fields_at_the_documented_offsets():
    pic = p.decode_picture_list(h("01000000 80000000 00000000") + documented_entry(file_number=3, rotation=8))[0]
    data = p.encode_picture_list([pic])
    assert data == h("01000000 80000000 00000000") + documented_entry(file_number=3, rotation=8)


def test_picture_list_rejections():
    with pytest.raises(ProtocolError, match="version"):
        p.decode_picture_list(h("02000000 80000000 00000000"))
    with pytest.raises(ProtocolError, match="whole number"):
        p.decode_picture_list(h("01000000 80000000 00000000") + bytes(100))
    assert p.decode_picture_list(h("01000000 80000000 00000000")) == []


# -- Wi-Fi framing (section 3) -------------------------------------------------------------


def test_wifi_read_header_magic_length_flags_command():
    header = p.encode_wifi_header(p.cdb_query_battery(), length=4, flags=p.WIFI_FLAG_READ)
    assert header == h("af55aafa 04000000 01000000 c60006") + bytes(13)
    assert len(header) == 28


def test_wifi_write_header_and_response_decode():
    expected = h("af55aafa 1e000000 00000000 c20001") + bytes(13)
    assert p.encode_wifi_header(p.cdb_load_file(), length=30, flags=0) == expected
    response = p.decode_wifi_header(h("af55aafa 1e000000 02000000 c20001") + bytes(13))
    assert (response.length, response.flags, response.command[:3]) == (30, 2, h("c20001"))
    with pytest.raises(ProtocolError, match="magic"):
        p.decode_wifi_header(h("af55aafb 1e000000 02000000 c20001") + bytes(13))


def test_callback_messages():
    assert p.parse_callback(b"[NewPictureAvailable] sha1-abc\x00") == ("[NewPictureAvailable]", "sha1-abc")
    assert p.parse_callback(b"[HeartbeatTick]\x00") == ("[HeartbeatTick]", "")
