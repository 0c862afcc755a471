"""White images: .TXT form (lytro-f01.md 1.8), data.C.N bundles (1.4), folder loading."""

from __future__ import annotations

import copy
import json
import logging

import numpy as np
import pytest

from analysis.errors import (
    ChecksumError,
    FormatError,
    MetadataError,
    MissingFileError,
    MissingSectionError,
    NoWhiteImageError,
    RawSizeError,
)
from analysis.formats.lfp import build_container, read_container, sha1_ref
from analysis.formats.raw12 import pack12
from analysis.formats.whites import (WhiteImage, load_white_images, parse_white_txt, read_bundle,
    white_txt_bytes, write_bundle, write_white_pair)

SERIAL = "A202110453"
W, H = 32, 16


@pytest.fixture()
def white_metadata(real_fixtures) -> dict:
    meta = json.loads((real_fixtures / "f01-frame-metadata.json").read_text())
    meta["image"]["width"], meta["image"]["height"] = W, H
    return meta


def _white(meta: dict, index: int, *, zoom: int = 981, focus: int = 582, duration: float = 0.05) -> WhiteImage:
    meta = copy.deepcopy(meta)
    meta["devices"]["lens"]["zoomStep"] = zoom
    meta["devices"]["lens"]["focusStep"] = focus
    meta["devices"]["shutter"]["frameExposureDuration"] = duration
    image = np.random.default_rng(index).integers(0, 4096, size=(H, W), dtype=np.uint16)
    return WhiteImage.from_image(f"MOD_{index:04d}", image, meta, {"camera": {"serialNumber": SERIAL}})


def _camera_files(whites: list[WhiteImage]) -> dict[str, bytes]:
    files = {}
    for w in whites:
        files[f"C:\\T1CALIB\\{w.name}.RAW"] = w.raw
        files[f"C:\\T1CALIB\\{w.name}.TXT"] = white_txt_bytes(w.metadata, w.private_metadata)
    return files


def test_txt_round_trip_and_layout(white_metadata):
    private = {"camera": {"serialNumber": SERIAL}}
    blob = white_txt_bytes(white_metadata, private)
    root = json.loads(blob)
    assert root["master"]["picture"]["frameArray"][0]["frame"]["metadata"] == white_metadata
    assert parse_white_txt(blob) == (white_metadata, private)
    assert white_txt_bytes(*parse_white_txt(blob)) == blob
    # The camera pads its files after the final brace.
    assert parse_white_txt(blob + b"\x00\x00\x1a\r\n") == (white_metadata, private)


@pytest.mark.parametrize("bad", [b"", b"not json", b'{"master": {}}', b"[1, 2]", b'{"image": {}}'])
def test_txt_bad_input(bad):
    with pytest.raises(MetadataError):
        parse_white_txt(bad)


def test_white_image_properties(white_metadata):
    w = _white(white_metadata, 3, zoom=943, focus=672, duration=0.0166)
    assert (w.serial, w.zoom_step, w.focus_step, w.exposure_duration_s) == (SERIAL, 943, 672, 0.0166)
    img = w.image()
    assert img.shape == (H, W) and img.dtype == np.uint16
    assert pack12(img) == w.raw
    assert w.sha1 == sha1_ref(w.raw)[5:]


def test_white_image_wrong_size(white_metadata):
    w = _white(white_metadata, 1)
    w.raw = w.raw[:-3]
    with pytest.raises(RawSizeError, match="MOD_0001"):
        w.image()


def test_bundle_round_trip_single(tmp_path):
    files = {"C:\\T1CALIB\\MOD_0000.RAW": b"\x01" * 30, "C:\\CALIB\\ACC.TXT": b"accel", "C:\\E.TXT": b""}
    paths = write_bundle(files, tmp_path)
    assert [p.name for p in paths] == ["data.C.0"]
    assert read_bundle(paths[0]) == files
    toc = read_container(paths[0].read_bytes()).toc
    assert "nextFile" not in toc
    assert [f["dataRef"] for f in toc["files"]] == [sha1_ref(v) for v in files.values()]


def test_bundle_splits_and_chains(tmp_path):
    files = {f"C:\\T1CALIB\\F{i}.RAW": bytes([i]) * 100 for i in range(7)}
    paths = write_bundle(files, tmp_path, max_bytes=250)
    assert [p.name for p in paths] == ["data.C.0", "data.C.1", "data.C.2", "data.C.3"]
    tocs = [read_container(p.read_bytes()).toc for p in paths]
    assert [t.get("nextFile") for t in tocs] == ["data.C.1", "data.C.2", "data.C.3", None]
    assert [len(t["files"]) for t in tocs] == [2, 2, 2, 1]
    back = read_bundle(paths[0])
    assert back == files and list(back) == list(files)
    assert read_bundle(paths[2]) == {k: files[k] for k in list(files)[4:]}  # starts mid-chain
    # Re-writing what was read gives the same bytes.
    again = tmp_path / "again"
    again.mkdir()
    assert [p.read_bytes() for p in write_bundle(back, again, max_bytes=250)] == [p.read_bytes() for p in paths]


def test_bundle_identical_files_share_a_section(tmp_path):
    files = {"a.TXT": b"same", "b.TXT": b"same"}
    (path,) = write_bundle(files, tmp_path)
    assert len(read_container(path.read_bytes()).sections) == 2
    assert read_bundle(path) == files


def test_bundle_missing_next_file(tmp_path):
    paths = write_bundle({"a": b"1" * 10, "b": b"2" * 10}, tmp_path, max_bytes=10)
    paths[1].unlink()
    with pytest.raises(MissingFileError, match="data.C.1"):
        read_bundle(paths[0])


def test_bundle_loop_detected(tmp_path):
    toc = {"files": [{"name": "a", "dataRef": sha1_ref(b"x")}], "nextFile": "data.C.0"}
    (tmp_path / "data.C.0").write_bytes(build_container(toc, [b"x"]))
    with pytest.raises(FormatError, match="loops"):
        read_bundle(tmp_path / "data.C.0")


def test_bundle_missing_data_section(tmp_path):
    toc = {"files": [{"name": "a", "dataRef": sha1_ref(b"x")}]}
    blob = build_container(toc, [b"x"])
    lfm = read_container(blob).sections[0]
    from analysis.formats.lfp import container_bytes
    (tmp_path / "data.C.0").write_bytes(container_bytes([lfm]))
    with pytest.raises(MissingSectionError, match="files\\[0\\].dataRef"):
        read_bundle(tmp_path / "data.C.0")


def test_bundle_corrupted(tmp_path):
    (path,) = write_bundle({"a": b"payload" * 10}, tmp_path)
    blob = bytearray(path.read_bytes())
    blob[-20] ^= 0xFF
    path.write_bytes(bytes(blob))
    with pytest.raises(ChecksumError):
        read_bundle(path)


def test_load_from_camera_folder(white_metadata, tmp_path, caplog):
    whites = [_white(white_metadata, i, zoom=900 + i) for i in range(3)]
    for w in whites:
        write_white_pair(w, tmp_path)
    (tmp_path / "MOD_0001.TXT").rename(tmp_path / "mod_0001.txt")  # letter case from FAT copies
    (tmp_path / "MOD_0009.RAW").write_bytes(b"\x00" * 768)  # no .TXT: skipped with a warning
    (tmp_path / "IMG_0001.RAW").write_bytes(b"")  # not a white image
    with caplog.at_level(logging.WARNING, logger="analysis.formats.whites"):
        loaded = load_white_images(tmp_path)
    assert "MOD_0009" in caplog.text
    assert [w.name for w in loaded] == ["MOD_0000", "MOD_0001", "MOD_0002"]
    for a, b in zip(whites, loaded):
        assert (a.raw, a.metadata, a.private_metadata) == (b.raw, b.metadata, b.private_metadata)
    assert [w.zoom_step for w in loaded] == [900, 901, 902]


@pytest.mark.parametrize("start", ["folder", "file"])
def test_load_from_bundle(white_metadata, tmp_path, start):
    whites = [_white(white_metadata, i) for i in range(4)]
    files = _camera_files(whites) | {"C:\\CALIB\\WIFI_MAC_ADDR.TXT": b"00:11"}
    write_bundle(files, tmp_path, max_bytes=1500)
    assert (tmp_path / "data.C.1").exists()
    loaded = load_white_images(tmp_path if start == "folder" else tmp_path / "data.C.0")
    assert [(w.name, w.raw, w.serial) for w in loaded] == [(w.name, w.raw, SERIAL) for w in whites]


def test_load_nothing_found(tmp_path):
    (tmp_path / "MOD_0000.RAW").write_bytes(b"")
    with pytest.raises(NoWhiteImageError, match="MOD_nnnn.RAW"):
        load_white_images(tmp_path)


def test_load_truncated_raw(white_metadata, tmp_path):
    raw_path, _ = write_white_pair(_white(white_metadata, 0), tmp_path)
    raw_path.write_bytes(raw_path.read_bytes()[:-1])
    with pytest.raises(RawSizeError, match="MOD_0000.RAW"):
        load_white_images(tmp_path)


def test_write_white_pair_refuses_wrong_size(white_metadata, tmp_path):
    w = _white(white_metadata, 0)
    w.raw = w.raw + b"\x00\x00\x00"
    with pytest.raises(RawSizeError):
        write_white_pair(w, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_loaded_raws_stay_on_disk(white_metadata, tmp_path):
    whites = [_white(white_metadata, i) for i in range(2)]
    write_bundle(_camera_files(whites), tmp_path)
    loaded = load_white_images(tmp_path)
    for a, b in zip(whites, loaded):
        assert b.raw_source is not None and b.raw_source.path == tmp_path / "data.C.0"
        assert b.raw_length == len(a.raw)
        assert b.sha1 == a.sha1  # from the bundle's dataRef, and equal to the bytes' SHA-1
        assert b.raw == a.raw and np.array_equal(b.image(), a.image())


def test_raw_changed_after_listing(white_metadata, tmp_path):
    raw_path, _ = write_white_pair(_white(white_metadata, 0), tmp_path)
    (loaded,) = load_white_images(tmp_path)
    kept = loaded.in_memory()
    raw_path.write_bytes(b"\x00" * 10)
    with pytest.raises(RawSizeError, match="cut short"):
        loaded.raw
    assert kept.raw_source is None and kept.image().shape == (H, W)
