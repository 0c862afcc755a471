"""One raw F01 exposure: the 12-bit sensor image with its metadata, read from and written to
an ``.lfp`` picture or the camera's ``.RAW`` + ``.TXT`` pair.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .atomic_write import write_all_atomic, write_atomic
from analysis.camera.model import CameraModel
from analysis.errors import FormatError, MetadataError, MissingFileError, RawSizeError
from .frame_metadata import check_packing, image_size, lookup, master_txt_bytes, parse_txt
from .lfp import build_container, json_bytes, read_container, sha1_ref
from .raw12 import pack12, unpack12

_TOC_VERSION = {"major": 1, "minor": 0, "provisionalDate": "2011-08-03"}


@dataclass(eq=False)
class Exposure:
    """A raw exposure.

    Attributes
    ----------
    image : ndarray of shape (H, W), uint16
        Raw sensor values 0..4095 as read (BGGR mosaic, no black subtraction).
    metadata : dict
        Frame metadata (``image``, ``devices``, ``modes``, ``camera``).
    private_metadata : dict
        Private metadata (camera and sensor serials); may be empty.
    sha1 : str
        Hex SHA-1 of the packed raw bytes, identifying the exposure's content. Computed
        from ``image`` when not given.
    name : str or None
        Where it came from, e.g. ``"IMG_0001"``.
    """

    image: np.ndarray
    metadata: dict
    private_metadata: dict = field(default_factory=dict)
    sha1: str | None = None
    name: str | None = None

    def __post_init__(self) -> None:
        if self.sha1 is None:
            self.sha1 = hashlib.sha1(self.raw_bytes()).hexdigest()

    @property
    def serial(self) -> str | None:
        """Camera serial number (``private_metadata.camera.serialNumber``), if known."""
        value = lookup(self.private_metadata, "camera.serialNumber")
        return None if value is None else str(value)

    @property
    def model(self) -> CameraModel:
        """The metadata camera model (lattice seed and optics)."""
        return CameraModel.from_metadata(self.metadata)

    def raw_bytes(self) -> bytes:
        """The image packed as the camera stores it, after checking it against the metadata.

        Raises
        ------
        RawSizeError
            If the image shape differs from ``image.width/height`` of the metadata.
        FormatError
            If it is not an integer image with values 0..4095, or the metadata declares
            another packing.
        """
        check_packing(self.metadata)
        width, height = image_size(self.metadata)
        image = np.asarray(self.image)
        if image.shape != (height, width):
            raise RawSizeError(f"image has shape {image.shape}, but its metadata says {height}x{width} "
                               "(image.height x image.width); make them agree before writing")
        if not np.issubdtype(image.dtype, np.integer):
            raise FormatError(f"image dtype is {image.dtype}; raw exposures hold integers 0..4095")
        if image.size and (image.min() < 0 or image.max() > 4095):
            raise FormatError(f"image values span {image.min()}..{image.max()}; a 12-bit raw holds 0..4095, "
                              "clip the image first")
        return pack12(image)


def _decode(raw: bytes | memoryview, metadata: dict, *, what: str) -> np.ndarray:
    check_packing(metadata)
    width, height = image_size(metadata)
    try:
        return unpack12(raw, width=width, height=height)
    except RawSizeError as exc:
        raise RawSizeError(f"{what}: {exc}") from None


def exposure_from_lfp_bytes(data: bytes | bytearray | memoryview, *, name: str | None = None) -> Exposure:
    """An exposure from the bytes of an F01 ``.lfp`` picture.

    The TOC's ``picture.frameArray[0].frame`` names the metadata, private metadata and image
    sections; each is found by its ref.

    Raises
    ------
    FormatError, TruncatedFileError, ChecksumError
        For a damaged container (see `analysis.formats.lfp.read_container`).
    MissingSectionError
        If the image (or metadata) section is not in the file, naming its ref.
    MetadataError
        If the TOC is not an F01 picture's, or metadata is not JSON.
    RawSizeError
        If the image section's size disagrees with the metadata.
    """
    what = name or "LFP picture"
    container = read_container(data)
    frame = lookup(container.toc, "picture")
    frames = frame.get("frameArray") if isinstance(frame, dict) else None
    if not isinstance(frames, list) or not frames or not isinstance(frames[0], dict) \
            or not isinstance(frames[0].get("frame"), dict):
        kind = "a data.C.N bundle (files[])" if "files" in container.toc else "not an F01 picture"
        raise MetadataError(f"{what}: the table of contents has no picture.frameArray[0].frame; it is {kind}. "
                            "Load bundles with analysis.formats.whites.load_white_images")
    refs = frames[0]["frame"]
    for key in ("metadataRef", "imageRef"):
        if not isinstance(refs.get(key), str):
            raise MetadataError(f"{what}: picture.frameArray[0].frame lacks {key}; not an F01 raw picture")
    metadata = container.json_section(refs["metadataRef"])
    private = container.json_section(refs["privateMetadataRef"]) if isinstance(
        refs.get("privateMetadataRef"), str) else {}
    image_section = container.section(refs["imageRef"])
    image = _decode(image_section.data, metadata, what=f"{what} image section {refs['imageRef']}")
    return Exposure(image=image, metadata=metadata, private_metadata=private,
                    sha1=image_section.sha1[len("sha1-"):], name=name)


def exposure_from_raw_pair(raw: bytes | bytearray | memoryview, txt: bytes | bytearray | memoryview, *,
                           name: str | None = None) -> Exposure:
    """An exposure from the camera's ``.RAW`` bytes and the ``.TXT`` beside it.

    The ``.TXT`` may be plain frame metadata (as the camera writes for pictures) or the
    ``master`` form that also carries private metadata (as `write_raw_pair` writes when
    there is private metadata, and as white images are stored).

    Raises
    ------
    MetadataError
        If the ``.TXT`` is not frame metadata JSON.
    RawSizeError
        If the raw size disagrees with ``image.width/height``.
    FormatError
        If the metadata declares a packing other than big-endian 12-bit.
    """
    what = name or "camera raw"
    metadata, private = parse_txt(txt, what=f"{what} .TXT")
    image = _decode(raw, metadata, what=f"{what} .RAW")
    return Exposure(image=image, metadata=metadata, private_metadata=private,
                    sha1=hashlib.sha1(raw).hexdigest(), name=name)


def companion(path: Path, suffix: str) -> Path | None:
    """The file beside ``path`` with the same stem and ``suffix``, letter case ignored, if any.

    Copies from the camera's FAT file system may come in either case.
    """
    exact = path.with_suffix(suffix.upper() if path.suffix.isupper() else suffix.lower())
    if exact.is_file():
        return exact
    wanted = (path.stem + suffix).lower()
    for candidate in path.parent.iterdir():
        if candidate.name.lower() == wanted and candidate.is_file():
            return candidate
    return None


def read_exposure(path: str | Path) -> Exposure:
    """Read an exposure from an ``.lfp`` picture, or a ``.RAW`` with its ``.TXT`` beside it.

    Either file of a ``.RAW``/``.TXT`` pair may be given; extensions in any letter case.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    MissingFileError
        If the other file of a pair is missing, naming the path expected.
    FormatError
        For an unknown extension, and every format error of the readers.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no exposure file at {path}")
    suffix = path.suffix.lower()
    if suffix == ".lfp":
        return exposure_from_lfp_bytes(path.read_bytes(), name=path.stem)
    if suffix in (".raw", ".txt"):
        other_suffix = ".TXT" if suffix == ".raw" else ".RAW"
        other = companion(path, other_suffix)
        if other is None:
            expected = path.with_suffix(other_suffix if path.suffix.isupper() else other_suffix.lower())
            raise MissingFileError(f"{path.name} needs {expected.name} beside it ({expected}); "
                                   f"copy both files of the pair from the camera")
        raw_path, txt_path = (path, other) if suffix == ".raw" else (other, path)
        return exposure_from_raw_pair(raw_path.read_bytes(), txt_path.read_bytes(), name=path.stem)
    raise FormatError(f"{path.name}: unknown exposure file type '{path.suffix}'; "
                      "give an .lfp picture or a camera .RAW with its .TXT")


def picture_toc(metadata_ref: str, private_metadata_ref: str, image_ref: str) -> dict:
    """The table of contents of an F01 raw picture (lytro-f01.md section 1.3)."""
    return {
        "picture": {
            "frameArray": [{
                "frame": {"metadataRef": metadata_ref, "privateMetadataRef": private_metadata_ref,
                          "imageRef": image_ref},
                "parameters": {"vendorContent": {"com.lytro.tags": {"darkFrame": False,
                                                                    "modulationFrame": False}}},
            }],
            "viewArray": [],
            "accelerationArray": [],
            "derivationArray": [],
        },
        "thumbnailArray": [],
        "version": dict(_TOC_VERSION),
    }


def lfp_bytes(exposure: Exposure) -> bytes:
    """The exposure as an F01 ``.lfp``: LFM, then metadata, private metadata and image LFCs.

    Raises
    ------
    RawSizeError, FormatError
        If the image does not fit its metadata (see `Exposure.raw_bytes`).
    """
    raw = exposure.raw_bytes()
    meta = json_bytes(exposure.metadata)
    private = json_bytes(exposure.private_metadata)
    toc = picture_toc(sha1_ref(meta), sha1_ref(private), sha1_ref(raw))
    return build_container(toc, [meta, private, raw])


def write_lfp(exposure: Exposure, path: str | Path) -> Path:
    """Write the exposure as an ``.lfp`` atomically (temp file, fsync, rename).

    Nothing is written if the exposure is invalid (see `lfp_bytes`).
    """
    return write_atomic(path, lfp_bytes(exposure))


def txt_bytes(exposure: Exposure) -> bytes:
    """The ``.TXT`` for the exposure's ``.RAW``.

    Plain frame metadata, as the camera writes it for pictures; when there is private
    metadata (the camera serial), the white-image ``master`` form, so the serial is kept.
    """
    if exposure.private_metadata:
        return master_txt_bytes(exposure.metadata, exposure.private_metadata)
    return json_bytes(exposure.metadata)


def write_raw_pair(exposure: Exposure, raw_path: str | Path) -> tuple[Path, Path]:
    """Write ``.RAW`` and ``.TXT`` (same stem, same folder) atomically.

    Both are written to temp files and renamed only once both are complete.

    Returns
    -------
    (raw_path, txt_path)
    """
    raw_path = Path(raw_path)
    if raw_path.suffix.lower() != ".raw":
        raise FormatError(f"{raw_path.name}: a camera raw must end in .RAW")
    txt_path = raw_path.with_suffix(".TXT" if raw_path.suffix == ".RAW" else ".txt")
    raw = exposure.raw_bytes()
    written = write_all_atomic({raw_path: raw, txt_path: txt_bytes(exposure)})
    return written[0], written[1]


__all__ = ["Exposure", "read_exposure", "exposure_from_lfp_bytes", "exposure_from_raw_pair", "lfp_bytes",
           "write_lfp", "write_raw_pair", "txt_bytes", "picture_toc", "companion"]
