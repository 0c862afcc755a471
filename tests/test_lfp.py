"""The LFP container against the byte layout of lytro-f01.md 1.1-1.2 and the real stripped file."""

from __future__ import annotations

import hashlib
import json

import pytest

from analysis.errors import ChecksumError, FormatError, MetadataError, MissingSectionError, TruncatedFileError
from analysis.formats.lfp import (build_container, container_bytes, inspect_container, read_container,
    read_container_file, section_bytes, sha1_ref)

STRIPPED = "f01-raw-image-section-stripped.lfp"
IMAGE_REF = "sha1-0360f825e6eed3c7c470fb79a755a54df07fae84"


@pytest.fixture()
def stripped(real_fixtures) -> bytes:
    return (real_fixtures / STRIPPED).read_bytes()


def _small_container(payloads=(b"first payload", b"x" * 32, b"")) -> tuple[bytes, dict]:
    toc = {"picture": {"frameArray": [{"frame": {f"p{i}Ref": sha1_ref(p) for i, p in enumerate(payloads)}}]}}
    return build_container(toc, list(payloads)), toc


# --- the real file -------------------------------------------------------------------------------

def test_real_stripped_file_parses_and_verifies(real_fixtures):
    container = read_container_file(real_fixtures / STRIPPED)
    assert [s.kind for s in container.sections] == ["LFM", "LFC", "LFC"]
    for s in container.sections:
        assert s.sha1 == "sha1-" + hashlib.sha1(s.data).hexdigest()
        assert (s.offset + 96) % 16 == 0
    frame = container.toc["picture"]["frameArray"][0]["frame"]
    assert frame["imageRef"] == IMAGE_REF
    assert container.missing_refs() == [("picture.frameArray[0].frame.imageRef", IMAGE_REF)]
    private = container.json_section(frame["privateMetadataRef"])
    assert private["camera"]["serialNumber"] == "A202110453"
    metadata = container.json_section(frame["metadataRef"])
    assert metadata["image"]["width"] == 3280
    assert metadata["camera"]["model"] == "F01"


def test_real_stripped_file_names_missing_image(stripped):
    container = read_container(stripped)
    with pytest.raises(MissingSectionError, match=IMAGE_REF) as info:
        container.section(IMAGE_REF)
    assert "imageRef" in str(info.value)


def test_real_file_rewrites_byte_for_byte(stripped):
    assert container_bytes(read_container(stripped).sections) == stripped


def test_real_file_inspection(stripped):
    report = inspect_container(stripped)
    assert [s.sha1_ok for s in report.sections] == [True, True, True]
    assert report.missing_refs == [("picture.frameArray[0].frame.imageRef", IMAGE_REF)]
    assert not report.ok


# --- byte layout ----------------------------------------------------------------------------------

def test_header_layout_matches_docs():
    data = b"hello lytro"
    blob = section_bytes("LFC", data)
    assert blob[:8] == bytes.fromhex("894C46430D0A1A0A")
    assert blob[8:12] == b"\x00\x00\x00\x00"
    assert int.from_bytes(blob[12:16], "big") == len(data)
    assert blob[16:61] == ("sha1-" + hashlib.sha1(data).hexdigest()).encode()
    assert blob[61:96] == b"\x00" * 35
    assert blob[96:96 + len(data)] == data
    assert len(blob) % 16 == 0 and set(blob[96 + len(data):]) == {0}
    assert section_bytes("LFM", b"{}")[:8] == bytes.fromhex("894C464D0D0A1A0A")


def test_built_container_layout():
    blob, _ = _small_container()
    assert blob[:16] == bytes.fromhex("894C46500D0A1A0A0000000100000000")
    container = read_container(blob)
    assert container.sections[0].kind == "LFM"  # F01 order: TOC first
    assert all(s.kind == "LFC" for s in container.sections[1:])
    assert all(s.offset % 16 == 0 for s in container.sections)


def test_build_round_trip():
    payloads = [b"first payload", b"x" * 32, b""]
    blob, toc = _small_container(payloads)
    container = read_container(blob)
    assert container.toc == toc
    for i, p in enumerate(payloads):
        assert bytes(container.section(sha1_ref(p)).data) == p
    assert container_bytes(container.sections) == blob


def test_lfm_found_wherever_it_sits():
    payload = b"image bytes"
    toc = {"picture": {"frameArray": [{"frame": {"imageRef": sha1_ref(payload)}}]}}
    blob = build_container(toc, [payload])
    lfm, lfc = read_container(blob).sections
    moved = container_bytes([lfc, lfm])  # Illum order: content first, TOC last
    container = read_container(moved)
    assert container.toc == toc
    assert bytes(container.section(sha1_ref(payload)).data) == payload


def test_tolerates_extra_nul_padding_between_sections():
    blob, toc = _small_container()
    lfm_end = 16 + 96 + len(read_container(blob).sections[0].data)
    lfm_end += -lfm_end % 16
    padded = blob[:lfm_end] + b"\x00" * 16 + blob[lfm_end:]
    assert read_container(padded).toc == toc


def test_build_refuses_dangling_ref():
    with pytest.raises(MissingSectionError, match=r"frame\.imageRef = sha1-0{40}"):
        build_container({"frame": {"imageRef": "sha1-" + "0" * 40, "nope": 1}}, [b"a"])


# --- bad input ------------------------------------------------------------------------------------

def test_not_an_lfp():
    with pytest.raises(FormatError, match="not an LFP"):
        read_container(b"GIF89a" + b"\x00" * 100)


@pytest.mark.parametrize("cut", [5, 16 + 50, 16 + 96 + 3])
def test_truncated_raises(stripped, cut):
    with pytest.raises(TruncatedFileError):
        read_container(stripped[:cut])


def test_truncated_last_section_raises(stripped):
    with pytest.raises(TruncatedFileError, match="cut short"):
        read_container(stripped[:-40])
    report = inspect_container(stripped[:-40])
    assert any("cut short" in p for p in report.problems)
    assert len(report.sections) == 2


def test_sha1_mismatch_raises(stripped):
    damaged = bytearray(stripped)
    second = read_container(stripped).sections[1]
    damaged[second.offset + 96 + 10] ^= 0x01
    with pytest.raises(ChecksumError, match=second.sha1):
        read_container(bytes(damaged))
    read_container(bytes(damaged), verify=False)  # the non-verifying path still reads it
    report = inspect_container(bytes(damaged))
    assert [s.sha1_ok for s in report.sections] == [True, False, True]


def test_garbage_between_sections_raises():
    blob, _ = _small_container()
    with pytest.raises(FormatError, match="no LFM/LFC section magic"):
        read_container(blob + b"junk" * 30)


def test_bad_ref_field_raises():
    blob = bytearray(_small_container()[0])
    blob[16 + 16:16 + 21] = b"md5--"
    with pytest.raises(FormatError, match="sha1-"):
        read_container(bytes(blob))


def test_non_json_toc_raises():
    blob = b"\x89LFP\r\n\x1a\n\x00\x00\x00\x01\x00\x00\x00\x00" + section_bytes("LFM", b"\xff not json")
    with pytest.raises(MetadataError):
        read_container(blob)
    blob = b"\x89LFP\r\n\x1a\n\x00\x00\x00\x01\x00\x00\x00\x00" + section_bytes("LFM", b"{broken")
    with pytest.raises(MetadataError, match="not valid JSON"):
        read_container(blob)


def test_non_json_section_raises():
    payload = b"\x00\x01 binary"
    blob = build_container({"metadataRef": sha1_ref(payload)}, [payload])
    with pytest.raises(MetadataError):
        read_container(blob).json_section(sha1_ref(payload))


def test_no_toc_raises():
    blob = b"\x89LFP\r\n\x1a\n\x00\x00\x00\x01\x00\x00\x00\x00" + section_bytes("LFC", b"data")
    with pytest.raises(MissingSectionError, match="LFM"):
        read_container(blob)


def test_trailing_bytes_after_json_tolerated():
    toc = {"a": 1}
    blob = b"\x89LFP\r\n\x1a\n\x00\x00\x00\x01\x00\x00\x00\x00" + section_bytes(
        "LFM", json.dumps(toc).encode() + b"\x00\x00\n")
    assert read_container(blob).toc == toc


def test_length_is_big_endian_int64():
    # Bytes 8-15 are one BE int64 (Lytro's '>8sq80s'): a non-zero high word means a huge section.
    blob = bytearray(_small_container()[0])
    length = int.from_bytes(blob[16 + 12:16 + 16], "big")
    blob[16 + 8] = 0x01
    with pytest.raises(TruncatedFileError, match=f"announces {(1 << 56) + length} bytes"):
        read_container(bytes(blob))
    blob[16 + 8] = 0x80
    with pytest.raises(FormatError, match="negative length"):
        read_container(bytes(blob))


def test_mutable_input_is_not_aliased():
    blob, toc = _small_container()
    buf = bytearray(blob)
    container = read_container(buf)
    buf[:] = b"\x00" * len(buf)  # the caller reuses its buffer
    assert container.toc == toc
    assert bytes(container.section(sha1_ref(b"first payload")).data) == b"first payload"
