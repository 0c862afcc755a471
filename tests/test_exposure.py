"""Exposures: .lfp and .RAW + .TXT round trips, the real metadata as a .TXT, and every bad input."""

from __future__ import annotations

import copy
import hashlib
import json

import numpy as np
import pytest

from analysis.errors import (
    FormatError,
    MetadataError,
    MissingFileError,
    MissingSectionError,
    RawSizeError,
    TruncatedFileError,
)
from analysis.formats.exposure import (Exposure, exposure_from_lfp_bytes, exposure_from_raw_pair, lfp_bytes,
    read_exposure, write_lfp, write_raw_pair)
from analysis.formats.lfp import read_container, sha1_ref
from analysis.formats.raw12 import pack12

SERIAL = "A202110453"


@pytest.fixture()
def real_metadata(real_fixtures) -> dict:
    return json.loads((real_fixtures / "f01-frame-metadata.json").read_text())


def _small(metadata: dict, width: int = 64, height: int = 48, seed: int = 0, private=None) -> Exposure:
    meta = copy.deepcopy(metadata)
    meta["image"]["width"], meta["image"]["height"] = width, height
    image = np.random.default_rng(seed).integers(0, 4096, size=(height, width), dtype=np.uint16)
    return Exposure(image=image, metadata=meta,
                    private_metadata={"camera": {"serialNumber": SERIAL}} if private is None else private,
                    name="IMG_0001")


def _assert_same(a: Exposure, b: Exposure) -> None:
    assert np.array_equal(a.image, b.image) and b.image.dtype == np.uint16
    assert a.metadata == b.metadata
    assert a.private_metadata == b.private_metadata
    assert a.sha1 == b.sha1 == hashlib.sha1(pack12(a.image)).hexdigest()


def test_sha1_is_of_packed_raw(real_metadata):
    exp = _small(real_metadata)
    assert exp.sha1 == hashlib.sha1(pack12(exp.image)).hexdigest()
    assert exp.serial == SERIAL
    assert exp.model.width == 64 and exp.model.height == 48


def test_lfp_round_trip_is_exact(real_metadata, tmp_path):
    exp = _small(real_metadata)
    path = write_lfp(exp, tmp_path / "IMG_0001.lfp")
    back = read_exposure(path)
    _assert_same(exp, back)
    assert back.name == "IMG_0001"
    assert lfp_bytes(back) == path.read_bytes()  # re-writing gives the same bytes


def test_lfp_structure_is_f01(real_metadata):
    exp = _small(real_metadata)
    container = read_container(lfp_bytes(exp))
    assert [s.kind for s in container.sections] == ["LFM", "LFC", "LFC", "LFC"]
    frame = container.toc["picture"]["frameArray"][0]["frame"]
    assert frame["imageRef"] == "sha1-" + exp.sha1
    assert container.json_section(frame["metadataRef"]) == exp.metadata
    assert container.json_section(frame["privateMetadataRef"])["camera"]["serialNumber"] == SERIAL
    assert [s.sha1 for s in container.sections[1:]] == [frame["metadataRef"], frame["privateMetadataRef"],
                                                         frame["imageRef"]]


@pytest.mark.parametrize("private", [None, {}])
def test_raw_pair_round_trip_is_exact(real_metadata, tmp_path, private):
    exp = _small(real_metadata, private=private)
    raw_path, txt_path = write_raw_pair(exp, tmp_path / "IMG_0001.RAW")
    assert txt_path == tmp_path / "IMG_0001.TXT"
    assert raw_path.read_bytes() == pack12(exp.image)
    for start in (raw_path, txt_path):  # either file of the pair may be given
        back = read_exposure(start)
        _assert_same(exp, back)
    again = tmp_path / "again"
    again.mkdir()
    write_raw_pair(back, again / "IMG_0001.RAW")
    assert (again / "IMG_0001.RAW").read_bytes() == raw_path.read_bytes()
    assert (again / "IMG_0001.TXT").read_bytes() == txt_path.read_bytes()


def test_real_metadata_works_as_txt(real_fixtures, tmp_path):
    txt = (real_fixtures / "f01-frame-metadata.json").read_bytes()
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 256, size=16_137_600, dtype=np.uint8).tobytes()  # one full-size F01 raw
    (tmp_path / "IMG_0007.raw").write_bytes(raw)
    (tmp_path / "img_0007.Txt").write_bytes(txt)  # any letter case, as copied from FAT
    exp = read_exposure(tmp_path / "IMG_0007.raw")
    assert exp.image.shape == (3280, 3280)
    assert exp.sha1 == hashlib.sha1(raw).hexdigest()
    assert exp.metadata["camera"]["model"] == "F01"
    assert exp.serial is None and exp.private_metadata == {}
    assert exp.model.optics.telecentric
    assert pack12(exp.image) == raw
    back = exposure_from_lfp_bytes(lfp_bytes(exp))
    assert back.sha1 == exp.sha1 and np.array_equal(back.image, exp.image)


def test_real_lfp_reports_missing_image(real_fixtures):
    with pytest.raises(MissingSectionError, match="sha1-0360f825e6eed3c7c470fb79a755a54df07fae84") as info:
        read_exposure(real_fixtures / "f01-raw-image-section-stripped.lfp")
    assert "imageRef" in str(info.value)


def test_upload_path_from_bytes(real_metadata):
    exp = _small(real_metadata, private={})
    back = exposure_from_raw_pair(pack12(exp.image), json.dumps(exp.metadata).encode() + b"\x00\x00", name="u")
    _assert_same(exp, back)
    assert back.name == "u"


# --- bad input ------------------------------------------------------------------------------------

def test_missing_txt_names_expected_path(real_metadata, tmp_path):
    exp = _small(real_metadata)
    raw_path, txt_path = write_raw_pair(exp, tmp_path / "IMG_0002.RAW")
    txt_path.unlink()
    with pytest.raises(MissingFileError, match="IMG_0002.TXT") as info:
        read_exposure(raw_path)
    assert isinstance(info.value, FileNotFoundError)


def test_missing_file():
    with pytest.raises(FileNotFoundError):
        read_exposure("/nonexistent/IMG_0001.lfp")


def test_unknown_extension(tmp_path):
    (tmp_path / "x.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(FormatError, match="unknown exposure file type"):
        read_exposure(tmp_path / "x.jpg")


def test_wrong_raw_size(real_metadata):
    exp = _small(real_metadata)
    with pytest.raises(RawSizeError, match="64x48"):
        exposure_from_raw_pair(pack12(exp.image)[:-3], json.dumps(exp.metadata).encode())


def test_wrong_image_section_size_in_lfp(real_metadata):
    exp = _small(real_metadata)
    blob = lfp_bytes(exp)
    small = copy.deepcopy(exp.metadata)
    small["image"]["width"] = 32
    from analysis.formats.lfp import build_container, json_bytes
    from analysis.formats.exposure import picture_toc
    meta, raw = json_bytes(small), pack12(exp.image)
    toc = picture_toc(sha1_ref(meta), sha1_ref(b"{}"), sha1_ref(raw))
    with pytest.raises(RawSizeError, match="image section"):
        exposure_from_lfp_bytes(build_container(toc, [meta, b"{}", raw]))
    assert exposure_from_lfp_bytes(blob).sha1 == exp.sha1


def test_non_json_metadata(real_metadata):
    exp = _small(real_metadata)
    with pytest.raises(MetadataError, match="not valid JSON"):
        exposure_from_raw_pair(pack12(exp.image), b"{\"image\": {\"width\": 64,")
    with pytest.raises(MetadataError):
        exposure_from_raw_pair(pack12(exp.image), b"\x89PNG\x00\xff")
    with pytest.raises(MetadataError, match="image.width"):
        exposure_from_raw_pair(pack12(exp.image), b'{"image": {"height": 48}}')


@pytest.mark.parametrize("packing", [{"endianness": "little", "bitsPerPixel": 12},
                                     {"endianness": "big", "bitsPerPixel": 10}])
def test_wrong_packing_declared(real_metadata, packing):
    exp = _small(real_metadata)
    meta = copy.deepcopy(exp.metadata)
    meta["image"]["rawDetails"]["pixelPacking"] = packing
    with pytest.raises(FormatError, match="pixelPacking"):
        exposure_from_raw_pair(pack12(exp.image), json.dumps(meta).encode())


def test_truncated_lfp(real_metadata):
    blob = lfp_bytes(_small(real_metadata))
    with pytest.raises(TruncatedFileError):
        exposure_from_lfp_bytes(blob[:-100])


def test_bundle_is_not_a_picture(tmp_path):
    from analysis.formats.whites import write_bundle
    (path,) = write_bundle({"C:\\T1CALIB\\MOD_0000.TXT": b"{}"}, tmp_path)
    with pytest.raises(MetadataError, match="bundle"):
        exposure_from_lfp_bytes(path.read_bytes())


@pytest.mark.parametrize("damage", ["too_bright", "wrong_shape", "float"])
def test_failed_write_leaves_nothing(real_metadata, tmp_path, damage):
    exp = _small(real_metadata)
    if damage == "too_bright":
        exp.image[3, 3] = 5000
    elif damage == "wrong_shape":
        exp.image = exp.image[:, :-2]
    else:
        exp.image = exp.image.astype(np.float32)
    with pytest.raises((FormatError, RawSizeError)):
        write_lfp(exp, tmp_path / "IMG.lfp")
    with pytest.raises((FormatError, RawSizeError)):
        write_raw_pair(exp, tmp_path / "IMG.RAW")
    assert list(tmp_path.iterdir()) == []


def test_written_files_are_readable_by_others(real_metadata, tmp_path):
    path = write_lfp(_small(real_metadata), tmp_path / "IMG.lfp")
    assert path.stat().st_mode & 0o777 == 0o644
    path.chmod(0o600)
    write_lfp(_small(real_metadata, seed=1), path)
    assert path.stat().st_mode & 0o777 == 0o600  # a replaced file keeps its mode


def test_failed_write_keeps_old_file(real_metadata, tmp_path):
    good = _small(real_metadata)
    path = write_lfp(good, tmp_path / "IMG.lfp")
    before = path.read_bytes()
    bad = _small(real_metadata)
    bad.image[0, 0] = 9999
    with pytest.raises(FormatError):
        write_lfp(bad, path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["IMG.lfp"]


def test_numpy_numbers_in_metadata_are_written_plainly(real_metadata, tmp_path):
    exp = _small(real_metadata)
    exp.metadata["image"]["width"] = np.int64(64)
    exp.metadata["devices"]["lens"]["zoomStep"] = np.int32(950)
    exp.metadata["devices"]["mla"]["rotation"] = np.float32(0.5)
    exp.metadata["image"]["color"]["ccmRgbToSrgbArray"] = np.eye(3).ravel()
    back = read_exposure(write_lfp(exp, tmp_path / "IMG.lfp"))
    assert back.metadata["image"]["width"] == 64
    assert back.metadata["devices"]["lens"]["zoomStep"] == 950
    assert back.metadata["devices"]["mla"]["rotation"] == 0.5
    assert back.metadata["image"]["color"]["ccmRgbToSrgbArray"] == [1, 0, 0, 0, 1, 0, 0, 0, 1]


@pytest.mark.parametrize("value", [float("nan"), object()])
def test_unwritable_metadata_leaves_nothing(real_metadata, tmp_path, value):
    exp = _small(real_metadata)
    exp.metadata["devices"]["lens"]["focalLength"] = value
    with pytest.raises(MetadataError, match="JSON"):
        write_lfp(exp, tmp_path / "IMG.lfp")
    with pytest.raises(MetadataError, match="JSON"):
        write_raw_pair(exp, tmp_path / "IMG.RAW")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("width", [None, "64", 0, -64, 63.5, float("inf"), True])
def test_bad_image_size_in_metadata(real_metadata, width):
    exp = _small(real_metadata)
    meta = copy.deepcopy(exp.metadata)
    meta["image"]["width"] = width
    with pytest.raises(MetadataError, match="image.width"):
        exposure_from_raw_pair(pack12(exp.image), json.dumps(meta).encode())


def test_no_damage_goes_unnoticed(real_metadata):
    """Flip single bytes anywhere in an .lfp: the reader either raises a named error or
    returns exactly the original exposure (for bytes no reader looks at)."""
    from analysis.errors import AnalysisError

    exp = _small(real_metadata, width=16, height=8)
    blob = lfp_bytes(exp)
    unnoticed = []
    for pos in range(len(blob)):
        damaged = bytearray(blob)
        damaged[pos] ^= 0x5A
        try:
            back = exposure_from_lfp_bytes(bytes(damaged))
        except AnalysisError:
            continue
        _assert_same(exp, back)
        unnoticed.append(int(pos))
    # Only the version word of the file header (bytes 8-11) is free to differ.
    assert unnoticed == [8, 9, 10, 11]
