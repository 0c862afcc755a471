"""White ("modulation") images: the camera's ``MOD_nnnn.RAW`` + ``.TXT`` files, their ``.TXT``
metadata, and the ``data.C.N`` backup bundles that carry them (lytro-f01.md sections 1.4, 1.8).
"""

from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from .atomic_write import write_all_atomic
from analysis.errors import FormatError, MetadataError, MissingFileError, NoWhiteImageError, RawSizeError
from .frame_metadata import check_packing, image_size, lookup, master_txt_bytes, parse_txt, unwrap_master
from .lfp import SECTION_HEADER_BYTES, Section, build_container, parse_json, read_container_file, sha1_ref
from .raw12 import pack12, unpack12

log = logging.getLogger(__name__)

BUNDLE_MAX_BYTES = 256 * 1024 * 1024
_BUNDLE_RE = re.compile(r"data\.C\.(\d+)")
_MOD_RE = re.compile(r"(MOD_\d+)\.(RAW|TXT)", re.IGNORECASE)


@dataclass(frozen=True)
class RawSource:
    """Where a white image's packed raw bytes lie: ``length`` bytes at ``offset`` of ``path``."""

    path: Path
    offset: int
    length: int

    def read(self) -> bytes:
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            data = fh.read(self.length)
        if len(data) != self.length:
            raise RawSizeError(f"{self.path} ended after {len(data)} of the {self.length} raw bytes expected "
                               f"at offset {self.offset}; the file changed or was cut short since it was listed")
        return data


@dataclass(init=False, eq=False)
class WhiteImage:
    """One white image: packed raw bytes and the metadata of its ``.TXT``.

    A camera holds some 60 white images of 16 MB each, so `load_white_images` does not keep
    their raws in memory: ``raw`` is read from its file each time it is asked for (give
    ``raw_source``); a white image built from bytes keeps them.
    """

    name: str
    metadata: dict
    private_metadata: dict

    def __init__(self, name: str, metadata: dict, private_metadata: dict | None = None,
                 raw: bytes | None = None, *, raw_source: RawSource | None = None,
                 sha1: str | None = None) -> None:
        if (raw is None) == (raw_source is None):
            raise ValueError("give a white image either its raw bytes or its raw_source, not both or neither")
        self.name = name
        self.metadata = metadata
        self.private_metadata = dict(private_metadata or {})
        self._raw = None if raw is None else bytes(raw)
        self.raw_source = raw_source
        self._sha1 = sha1

    @property
    def raw(self) -> bytes:
        """The packed 12-bit raw bytes (read from ``raw_source`` on each access if not in memory)."""
        if self._raw is not None:
            return self._raw
        assert self.raw_source is not None
        return self.raw_source.read()

    @raw.setter
    def raw(self, value: bytes) -> None:
        self._raw, self.raw_source, self._sha1 = bytes(value), None, None

    def in_memory(self) -> "WhiteImage":
        """This white image with its raw read into memory (to keep it after its files go away)."""
        return WhiteImage(self.name, self.metadata, self.private_metadata, raw=self.raw, sha1=self._sha1)

    @property
    def raw_length(self) -> int:
        return len(self._raw) if self._raw is not None else self.raw_source.length  # type: ignore[union-attr]

    @classmethod
    def from_image(cls, name: str, image: np.ndarray, metadata: dict,
                   private_metadata: dict | None = None) -> "WhiteImage":
        """Pack a uint16 image (values 0..4095) into a white image."""
        return cls(name, metadata, private_metadata, raw=pack12(image))

    @property
    def serial(self) -> str | None:
        value = lookup(self.private_metadata, "camera.serialNumber")
        return None if value is None else str(value)

    @property
    def zoom_step(self) -> int | None:
        value = lookup(self.metadata, "devices.lens.zoomStep")
        return None if value is None else int(value)

    @property
    def focus_step(self) -> int | None:
        value = lookup(self.metadata, "devices.lens.focusStep")
        return None if value is None else int(value)

    @property
    def exposure_duration_s(self) -> float | None:
        value = lookup(self.metadata, "devices.shutter.frameExposureDuration")
        return None if value is None else float(value)

    @property
    def sha1(self) -> str:
        """Hex SHA-1 of the packed raw bytes (computed once)."""
        if self._sha1 is None:
            self._sha1 = hashlib.sha1(self.raw).hexdigest()
        return self._sha1

    def image(self) -> np.ndarray:
        """The raw image, ndarray of shape (H, W), uint16, values 0..4095.

        Raises
        ------
        RawSizeError
            If the raw size disagrees with the metadata's ``image.width/height``.
        """
        check_packing(self.metadata)
        width, height = image_size(self.metadata)
        try:
            return unpack12(self.raw, width=width, height=height)
        except RawSizeError as exc:
            raise RawSizeError(f"white image {self.name}: {exc}") from None


def parse_white_txt(data: bytes | bytearray | memoryview) -> tuple[dict, dict]:
    """Frame and private metadata of a white-image ``.TXT``.

    The root is ``master.picture.frameArray[0].frame.{metadata, privateMetadata}``; bytes
    after the final ``}`` (the camera pads) are ignored.

    Raises
    ------
    MetadataError
        If it is not JSON or not of that form.
    """
    root = parse_json(data, what="white-image .TXT")
    if not isinstance(root, dict):
        raise MetadataError(f"white-image .TXT holds a JSON {type(root).__name__}, not an object")
    return unwrap_master(root, what="white-image .TXT")


def white_txt_bytes(metadata: dict, private_metadata: dict) -> bytes:
    """A white-image ``.TXT`` (inverse of `parse_white_txt`)."""
    return master_txt_bytes(metadata, private_metadata)


def _bundle_index(path: Path) -> int | None:
    m = _BUNDLE_RE.fullmatch(path.name)
    return int(m.group(1)) if m else None


def read_bundle(path: str | Path) -> dict[str, bytes]:
    """All files of a ``data.C.N`` backup chain, starting at ``path``.

    Each container's TOC lists ``files[]`` (``name``, ``dataRef``) and may name the next
    container in ``nextFile``, looked up in the same folder.

    Returns
    -------
    dict
        Camera path (e.g. ``C:\\T1CALIB\\MOD_0000.RAW``) -> file bytes, in chain order.

    Raises
    ------
    MissingFileError
        If a ``nextFile`` is not in the folder.
    FormatError
        If the chain loops, or a TOC has no ``files[]``; and every container error.
    MissingSectionError
        If a ``dataRef`` names no section.
    """
    return {name: bytes(section.data) for _, name, section in iter_bundle(path)}


def iter_bundle(path: str | Path) -> Iterator[tuple[Path, str, Section]]:
    """Walk a ``data.C.N`` chain: ``(container_path, file_name, section)`` for each file.

    Only one container is held in memory at a time; a section's ``offset`` locates its data
    (at ``offset + 96``) in ``container_path``. Raises as `read_bundle`.
    """
    path = Path(path)
    seen: list[Path] = []
    current: Path | None = path
    while current is not None:
        if current.resolve() in seen:
            chain = " -> ".join(p.name for p in seen + [current.resolve()])
            raise FormatError(f"backup bundle chain loops ({chain}); the nextFile fields are damaged")
        if not current.is_file():
            named_by = f"named by nextFile of {seen[-1].name}" if seen else "the bundle asked for"
            raise MissingFileError(f"backup bundle {current} is missing ({named_by}); "
                                   "copy the whole data.C.* set into one folder")
        seen.append(current.resolve())
        container = read_container_file(current)
        entries = container.toc.get("files")
        if not isinstance(entries, list):
            raise FormatError(f"{current.name} has no files[] in its table of contents; it is not a "
                              "data.C.N backup bundle (a picture? use read_exposure)")
        for k, entry in enumerate(entries):
            if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) \
                    or not isinstance(entry.get("dataRef"), str):
                raise MetadataError(f"{current.name}: files[{k}] lacks a 'name' or 'dataRef' string")
            yield current, entry["name"], container.section(entry["dataRef"])
        nxt = container.toc.get("nextFile")
        # nextFile is a bare file name; never follow it out of the folder.
        current = current.parent / Path(nxt.replace("\\", "/")).name if isinstance(nxt, str) and nxt else None


def write_bundle(files: Mapping[str, bytes | bytearray | memoryview], folder: str | Path, *,
                 max_bytes: int = BUNDLE_MAX_BYTES) -> list[Path]:
    """Write files as a ``data.C.0``, ``data.C.1``, ... chain (inverse of `read_bundle`).

    A new container is started before the payloads of one would exceed ``max_bytes``
    (a single larger file gets a container of its own). All containers are written to temp
    files first and renamed into place only when all are complete.

    Returns
    -------
    list of Path
        The containers, in chain order.
    """
    folder = Path(folder)
    if max_bytes <= 0:
        raise ValueError(f"max_bytes must be positive, not {max_bytes}")
    groups: list[list[tuple[str, bytes | bytearray | memoryview]]] = [[]]
    size = 0
    for name, data in files.items():
        if groups[-1] and size + len(data) > max_bytes:
            groups.append([])
            size = 0
        groups[-1].append((name, data))
        size += len(data)
    out = {}
    for k, group in enumerate(groups):
        toc: dict = {"files": [{"name": name, "dataRef": sha1_ref(data)} for name, data in group]}
        if k + 1 < len(groups):
            toc["nextFile"] = f"data.C.{k + 1}"
        out[folder / f"data.C.{k}"] = build_container(toc, [data for _, data in group])
    return write_all_atomic(out)


def _mod_key(name: str) -> tuple[str, str] | None:
    """``("MOD_0003", "RAW")`` for a white-image file name or camera path, else None."""
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    m = _MOD_RE.fullmatch(base)
    return (m.group(1).upper(), m.group(2).upper()) if m else None


def _check_raw_length(name: str, length: int, metadata: dict, where: str) -> None:
    check_packing(metadata)
    width, height = image_size(metadata)
    if length != width * height * 3 // 2:
        raise RawSizeError(f"{name}.RAW in {where} has {length} bytes, but its .TXT says {width}x{height} "
                           f"({width * height * 3 // 2} bytes packed); the file is truncated, copy it again")


def load_white_images(source: str | Path) -> list[WhiteImage]:
    """All white images in a folder of ``MOD_nnnn.RAW``/``.TXT``, a folder holding ``data.C.0``,
    or a ``data.C.N`` file.

    Metadata is read at once; raws stay on disk (``WhiteImage.raw_source``) and are read
    when asked for. Pairs lacking one of their files are skipped with a logged warning.

    Returns
    -------
    list of WhiteImage, sorted by name.

    Raises
    ------
    NoWhiteImageError
        If no complete pair is found.
    MetadataError, RawSizeError
        If a pair's ``.TXT`` is not metadata or its ``.RAW`` has the wrong size.
    FormatError, MissingFileError
        For a damaged bundle chain (see `read_bundle`).
    """
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"no white-image folder or bundle at {source}")
    raws: dict[str, tuple[RawSource, str | None]] = {}
    txts: dict[str, bytes] = {}
    bundle = source if source.is_file() else source / "data.C.0"
    if source.is_file() and _bundle_index(source) is None:
        raise FormatError(f"{source.name} is not a data.C.N bundle; give it, or a folder of MOD_nnnn files")
    if bundle.is_file():
        for container_path, name, section in iter_bundle(bundle):
            key = _mod_key(name)
            if key is None:
                continue
            if key[1] == "RAW":
                raws[key[0]] = (RawSource(container_path, section.offset + SECTION_HEADER_BYTES, section.length),
                                section.sha1[len("sha1-"):])
            else:
                txts[key[0]] = bytes(section.data)
    else:
        for path in sorted(source.iterdir()):
            key = _mod_key(path.name)
            if key is None or not path.is_file():
                continue
            if key[1] == "RAW":
                raws[key[0]] = (RawSource(path, 0, path.stat().st_size), None)
            else:
                txts[key[0]] = path.read_bytes()
    whites = []
    for stem in sorted(set(raws) | set(txts)):
        if stem not in raws or stem not in txts:
            log.warning("white image %s in %s has no .%s; skipped", stem, source,
                        "RAW" if stem not in raws else "TXT")
            continue
        metadata, private = parse_txt(txts[stem], what=f"{stem}.TXT in {source}")
        raw_source, sha1 = raws[stem]
        _check_raw_length(stem, raw_source.length, metadata, str(source))
        whites.append(WhiteImage(stem, metadata, private, raw_source=raw_source, sha1=sha1))
    if not whites:
        raise NoWhiteImageError(
            f"no white images in {source}: looked for MOD_nnnn.RAW with MOD_nnnn.TXT (as in the camera's "
            "C:\\T1CALIB\\) in the folder or its data.C.N backup bundles; pull the calibration files "
            "from the camera first")
    return whites


def write_white_pair(white: WhiteImage, folder: str | Path) -> tuple[Path, Path]:
    """Write ``<name>.RAW`` and ``<name>.TXT`` into ``folder`` as the camera stores them (atomically).

    Raises
    ------
    RawSizeError
        If the raw size disagrees with the metadata (nothing is written).
    """
    folder = Path(folder)
    raw = white.raw
    _check_raw_length(white.name, len(raw), white.metadata, str(folder))
    raw_path, txt_path = folder / f"{white.name}.RAW", folder / f"{white.name}.TXT"
    write_all_atomic({raw_path: raw, txt_path: white_txt_bytes(white.metadata, white.private_metadata)})
    return raw_path, txt_path
