"""What a Lytro file holds and what is wrong with it, without raising: the core of
``plenodust inspect``.

`inspect_file` recognises an ``.lfp`` picture, a ``data.C.N`` bundle, a camera ``.RAW``
+ ``.TXT`` pair, a white-image ``.TXT`` and a frame-metadata JSON, and reports sections,
SHA-1 status, refs without a section, the key metadata, and every problem found.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from analysis.errors import FormatError
from .exposure import companion
from .frame_metadata import check_packing, image_size, lookup, parse_txt
from .lfp import FILE_MAGIC, LfpContainer, inspect_container, parse_json

KIND_PICTURE = "lfp picture"
KIND_BUNDLE = "lfp bundle"
KIND_LFP_OTHER = "lfp (unknown table of contents)"
KIND_RAW_PAIR = "camera raw pair"
KIND_WHITE_TXT = "white txt"
KIND_FRAME_JSON = "frame json"
KIND_UNKNOWN = "unknown"

_KEY_FIELDS = {
    "camera": ("camera.make", "camera.model", "camera.firmware"),
    "lens": ("devices.lens.focalLength", "devices.lens.fNumber", "devices.lens.zoomStep",
             "devices.lens.focusStep", "devices.lens.exitPupilOffset"),
    "mla": ("devices.mla.lensPitch", "devices.mla.rotation", "devices.mla.scaleFactor",
            "devices.mla.sensorOffset"),
    "image": ("image.width", "image.height"),
}


@dataclass
class FileReport:
    """Everything `inspect_file` found. ``readable`` is False when the file could not be
    recognised or read at all; ``problems`` lists what is wrong with a readable one."""

    path: str
    kind: str = KIND_UNKNOWN
    size_bytes: int = 0
    readable: bool = True
    sections: list[dict] = field(default_factory=list)
    missing_refs: list[dict] = field(default_factory=list)
    files: list[dict] = field(default_factory=list)
    next_file: str | None = None
    raw_sha1: str | None = None
    metadata: dict = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.readable and not self.problems

    def as_dict(self) -> dict:
        out = asdict(self)
        out["ok"] = self.ok
        return out


def key_metadata(metadata: dict, private_metadata: dict | None = None) -> dict:
    """Serial, camera make/model/firmware, lens, MLA and image size from frame metadata.

    Fields absent from the metadata are left out.
    """
    out: dict[str, Any] = {"serial": lookup(private_metadata or {}, "camera.serialNumber")}
    for group, paths in _KEY_FIELDS.items():
        values = {p.rsplit(".", 1)[-1]: lookup(metadata, p) for p in paths}
        out[group] = {k: v for k, v in values.items() if v is not None}
    taken = lookup(metadata, "devices.clock.zuluTime")
    if taken is not None:
        out["taken"] = taken
    duration = lookup(metadata, "devices.shutter.frameExposureDuration")
    if duration is not None:
        out["exposure_duration_s"] = duration
    return out


def _check_raw(report: FileReport, raw_len: int, metadata: dict, what: str) -> None:
    try:
        check_packing(metadata)
        width, height = image_size(metadata)
    except FormatError as exc:
        report.problems.append(str(exc))
        return
    if raw_len != width * height * 3 // 2:
        report.problems.append(f"{what} has {raw_len} bytes, but a {width}x{height} 12-bit packed image "
                               f"needs {width * height * 3 // 2}")


def _json_of(container: LfpContainer, ref: Any, report: FileReport, what: str) -> dict | None:
    if not isinstance(ref, str):
        return None
    bad = {s["sha1"] for s in report.sections if not s["sha1_ok"]}
    try:
        section = container.section(ref)
    except FormatError:
        return None  # already listed in missing_refs
    if ref in bad:
        return None  # its data cannot be trusted; the checksum problem is listed
    try:
        value = parse_json(section.data, what=f"{what} section {ref}")
    except FormatError as exc:
        report.problems.append(str(exc))
        return None
    if not isinstance(value, dict):
        report.problems.append(f"{what} section {ref} is not a JSON object")
        return None
    return value


def _inspect_lfp(report: FileReport, path: Path, data: bytes) -> None:
    found = inspect_container(data)
    report.sections = [asdict(s) for s in found.sections]
    report.missing_refs = [{"path": p, "ref": r} for p, r in found.missing_refs]
    report.problems.extend(found.problems)
    if found.container is None:
        report.kind = KIND_LFP_OTHER
        return
    container = found.container
    toc = container.toc
    if isinstance(toc.get("picture"), dict):
        report.kind = KIND_PICTURE
        frames = lookup(toc, "picture.frameArray")
        frame = frames[0].get("frame") if isinstance(frames, list) and frames and isinstance(frames[0], dict) \
            else None
        frame = frame if isinstance(frame, dict) else {}
        metadata = _json_of(container, frame.get("metadataRef"), report, "metadata")
        private = _json_of(container, frame.get("privateMetadataRef"), report, "private metadata")
        if metadata is not None:
            report.metadata = key_metadata(metadata, private)
            image_ref = frame.get("imageRef")
            verified = {s["sha1"] for s in report.sections if s["sha1_ok"]}
            if isinstance(image_ref, str) and image_ref in verified:
                report.raw_sha1 = image_ref[len("sha1-"):]
                _check_raw(report, container.section(image_ref).length, metadata, f"image section {image_ref}")
        elif not isinstance(frame.get("metadataRef"), str):
            report.problems.append("picture.frameArray[0].frame has no metadataRef")
    elif isinstance(toc.get("files"), list):
        report.kind = KIND_BUNDLE
        present = {s.sha1: s.length for s in container.sections}
        for entry in toc["files"]:
            if isinstance(entry, dict):
                ref = entry.get("dataRef")
                report.files.append({"name": entry.get("name"), "dataRef": ref, "length": present.get(ref)})
        nxt = toc.get("nextFile")
        report.next_file = nxt if isinstance(nxt, str) and nxt else None
        if report.next_file and not (path.parent / Path(report.next_file.replace("\\", "/")).name).is_file():
            report.problems.append(f"nextFile {report.next_file} is not beside this file; the rest of the "
                                   "backup chain is missing")
    else:
        report.kind = KIND_LFP_OTHER


def _inspect_pair(report: FileReport, path: Path) -> None:
    report.kind = KIND_RAW_PAIR
    is_raw = path.suffix.lower() == ".raw"
    other = companion(path, ".TXT" if is_raw else ".RAW")
    raw_path, txt_path = (path, other) if is_raw else (other, path)
    if other is None:
        report.problems.append(f"{path.name} has no {'.TXT' if is_raw else '.RAW'} beside it")
    metadata = None
    if txt_path is not None:
        try:
            metadata, private = parse_txt(txt_path.read_bytes(), what=txt_path.name)
            report.metadata = key_metadata(metadata, private)
        except FormatError as exc:
            report.problems.append(str(exc))
    if raw_path is not None:
        raw = raw_path.read_bytes()
        report.raw_sha1 = hashlib.sha1(raw).hexdigest()
        if metadata is not None:
            _check_raw(report, len(raw), metadata, raw_path.name)


def _inspect_json(report: FileReport, data: bytes) -> None:
    try:
        root = parse_json(data, what="file")
    except FormatError as exc:
        report.readable = False
        report.problems.append(f"neither an LFP container nor JSON metadata: {exc}")
        return
    if isinstance(root, dict) and "master" in root:
        report.kind = KIND_WHITE_TXT
    elif isinstance(root, dict) and "image" in root:
        report.kind = KIND_FRAME_JSON
    else:
        report.readable = False
        report.problems.append("JSON, but neither frame metadata ('image' at the top) nor a white-image "
                               ".TXT ('master' at the top)")
        return
    try:
        metadata, private = parse_txt(data)
    except FormatError as exc:
        report.problems.append(str(exc))
        return
    report.metadata = key_metadata(metadata, private)


def inspect_file(path: str | Path) -> FileReport:
    """Report on one Lytro file without raising for anything wrong in it.

    Raises
    ------
    FileNotFoundError, PermissionError, IsADirectoryError
        Only if the file itself cannot be opened.
    """
    path = Path(path)
    data = path.read_bytes()
    report = FileReport(path=str(path), size_bytes=len(data))
    if data[:8] == FILE_MAGIC or (len(data) < 8 and data and FILE_MAGIC.startswith(data)):
        _inspect_lfp(report, path, data)
    elif path.suffix.lower() == ".raw" or (path.suffix.lower() == ".txt" and _has_raw_beside(path)):
        del data  # the pair is read again by parts
        _inspect_pair(report, path)
    else:
        _inspect_json(report, data)
    return report


def _has_raw_beside(path: Path) -> bool:
    return companion(path, ".RAW") is not None
