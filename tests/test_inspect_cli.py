"""`plenodust inspect`: JSON report and exit status for every kind of file, sound or damaged."""

from __future__ import annotations

import json

import numpy as np
import pytest

from analysis.formats.exposure import Exposure, lfp_bytes, write_lfp, write_raw_pair
from analysis.formats.lfp import read_container
from analysis.formats.whites import WhiteImage, white_txt_bytes, write_bundle
from service.cli.main import main

IMAGE_REF = "sha1-0360f825e6eed3c7c470fb79a755a54df07fae84"


def _inspect(path, capsys) -> tuple[int, dict]:
    code = main(["inspect", str(path)])
    out = capsys.readouterr().out
    return code, (json.loads(out) if out.strip() else {})


@pytest.fixture()
def exposure(real_fixtures) -> Exposure:
    meta = json.loads((real_fixtures / "f01-frame-metadata.json").read_text())
    meta["image"]["width"], meta["image"]["height"] = 32, 16
    image = np.random.default_rng(5).integers(0, 4096, size=(16, 32), dtype=np.uint16)
    return Exposure(image=image, metadata=meta, private_metadata={"camera": {"serialNumber": "A1"}})


def test_real_stripped_lfp(real_fixtures, capsys):
    code, rep = _inspect(real_fixtures / "f01-raw-image-section-stripped.lfp", capsys)
    assert code == 1
    assert rep["kind"] == "lfp picture"
    assert [s["kind"] for s in rep["sections"]] == ["LFM", "LFC", "LFC"]
    assert all(s["sha1_ok"] for s in rep["sections"])
    assert rep["missing_refs"] == [{"path": "picture.frameArray[0].frame.imageRef", "ref": IMAGE_REF}]
    assert any(IMAGE_REF in p for p in rep["problems"])
    md = rep["metadata"]
    assert md["serial"] == "A202110453"
    assert md["camera"]["model"] == "F01" and md["camera"]["firmware"].startswith("v1.0a60")
    assert md["lens"]["zoomStep"] == 981 and md["lens"]["focusStep"] == 721
    assert md["lens"]["exitPupilOffset"]["z"] == pytest.approx(0.11638, abs=1e-5)
    assert md["mla"]["scaleFactor"]["y"] == pytest.approx(1.000439, abs=1e-6)
    assert md["mla"]["rotation"] == pytest.approx(-0.000282, abs=1e-6)


def test_real_frame_json(real_fixtures, capsys):
    code, rep = _inspect(real_fixtures / "f01-frame-metadata.json", capsys)
    assert code == 0 and rep["ok"]
    assert rep["kind"] == "frame json"
    assert rep["metadata"]["lens"]["exitPupilOffset"]["z"] == 10000
    assert rep["metadata"]["serial"] is None


def test_sound_lfp(exposure, tmp_path, capsys):
    path = write_lfp(exposure, tmp_path / "IMG_0001.lfp")
    code, rep = _inspect(path, capsys)
    assert code == 0 and rep["ok"] and rep["problems"] == []
    assert rep["raw_sha1"] == exposure.sha1
    assert rep["metadata"]["serial"] == "A1"
    assert len(rep["sections"]) == 4 and rep["size_bytes"] == path.stat().st_size


def test_corrupted_lfp(exposure, tmp_path, capsys):
    blob = bytearray(lfp_bytes(exposure))
    image = read_container(bytes(blob)).sections[3]
    blob[image.offset + 96 + 5] ^= 0x10
    (tmp_path / "bad.lfp").write_bytes(bytes(blob))
    code, rep = _inspect(tmp_path / "bad.lfp", capsys)
    assert code == 1
    assert [s["sha1_ok"] for s in rep["sections"]] == [True, True, True, False]
    assert rep["raw_sha1"] is None  # a damaged image has no trustworthy identity
    assert rep["metadata"]["serial"] == "A1"  # the sound sections still report


def test_truncated_lfp(exposure, tmp_path, capsys):
    (tmp_path / "cut.lfp").write_bytes(lfp_bytes(exposure)[:-200])
    code, rep = _inspect(tmp_path / "cut.lfp", capsys)
    assert code == 1
    assert len(rep["sections"]) == 3
    assert any("cut short" in p for p in rep["problems"])


def test_raw_pair(exposure, tmp_path, capsys):
    raw_path, txt_path = write_raw_pair(exposure, tmp_path / "IMG_0002.RAW")
    for start in (raw_path, txt_path):
        code, rep = _inspect(start, capsys)
        assert code == 0 and rep["kind"] == "camera raw pair"
        assert rep["raw_sha1"] == exposure.sha1
    raw_path.write_bytes(raw_path.read_bytes()[:-3])
    code, rep = _inspect(raw_path, capsys)
    assert code == 1 and any("12-bit packed" in p for p in rep["problems"])
    txt_path.unlink()
    code, rep = _inspect(raw_path, capsys)
    assert code == 1 and any(".TXT" in p for p in rep["problems"])


def test_bundle_and_white_txt(exposure, tmp_path, capsys):
    white = WhiteImage.from_image("MOD_0000", exposure.image, exposure.metadata, exposure.private_metadata)
    txt = white_txt_bytes(white.metadata, white.private_metadata)
    paths = write_bundle({"C:\\T1CALIB\\MOD_0000.RAW": white.raw, "C:\\T1CALIB\\MOD_0000.TXT": txt},
                         tmp_path, max_bytes=len(white.raw))
    code, rep = _inspect(paths[0], capsys)
    assert code == 0 and rep["kind"] == "lfp bundle"
    assert rep["files"] == [{"name": "C:\\T1CALIB\\MOD_0000.RAW", "dataRef": "sha1-" + white.sha1,
                             "length": len(white.raw)}]
    assert rep["next_file"] == "data.C.1"
    code, rep = _inspect(paths[1], capsys)
    assert code == 0 and rep["next_file"] is None
    paths[1].unlink()
    code, rep = _inspect(paths[0], capsys)
    assert code == 1 and any("data.C.1" in p for p in rep["problems"])
    (tmp_path / "MOD_0000.TXT").write_bytes(txt + b"\x00\x00")
    code, rep = _inspect(tmp_path / "MOD_0000.TXT", capsys)
    assert code == 0 and rep["kind"] == "white txt"
    assert rep["metadata"]["serial"] == "A1"


@pytest.mark.parametrize("content", [b"GIF89a\x00\x00", b"", b"[1, 2, 3]"])
def test_unrecognised_file(tmp_path, capsys, content):
    (tmp_path / "x.bin").write_bytes(content)
    code, rep = _inspect(tmp_path / "x.bin", capsys)
    assert code == 2 and not rep["readable"] and rep["problems"]


def test_missing_file_and_usage(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "none.lfp")]) == 2
    assert "cannot read" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["inspect"])
    assert info.value.code == 2


@pytest.mark.parametrize("content", [b"\x89LFP\r\n\x1a\nxxxxxxxx",
                                     b"\x89LFP\r\n\x1a\n\x00\x00\x00\x01\x00\x00\x00\x00\x89LFM"])
def test_damaged_lfp_header_is_a_problem(tmp_path, capsys, content):
    (tmp_path / "x.lfp").write_bytes(content)
    code, rep = _inspect(tmp_path / "x.lfp", capsys)
    assert code == 1 and rep["readable"] and rep["sections"] == [] and rep["problems"]
