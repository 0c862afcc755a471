"""Frame metadata JSON as the F01 stores it: picture ``.TXT`` files and white-image ``.TXT`` files.

A picture's ``.TXT`` (and the ``metadataRef`` section of an ``.lfp``) is the frame metadata
itself: ``{"type", "image", "devices", "modes", "camera"}``. A white image's ``.TXT`` wraps
frame and private metadata as ``master.picture.frameArray[0].frame.{metadata, privateMetadata}``
(lytro-f01.md sections 1.6 and 1.8). `parse_txt` reads either form.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

from analysis.errors import FormatError, MetadataError
from .lfp import json_bytes, parse_json


def parse_txt(data: bytes | bytearray | memoryview, *, what: str = "metadata .TXT") -> tuple[dict, dict]:
    """Frame metadata and private metadata from a ``.TXT`` in either form.

    Returns
    -------
    (metadata, private_metadata) : tuple of dict
        ``private_metadata`` is empty for the plain frame-metadata form.

    Raises
    ------
    MetadataError
        Not JSON, not an object, or a ``master`` wrapper without ``frame.metadata``.
    """
    root = parse_json(data, what=what)
    if not isinstance(root, dict):
        raise MetadataError(f"{what} holds a JSON {type(root).__name__}, not an object of frame metadata")
    if "master" in root:
        return unwrap_master(root, what=what)
    if "image" not in root:
        raise MetadataError(f"{what} has neither 'image' (frame metadata) nor 'master' (white-image form) "
                            "at its top level; is it a Lytro F01 metadata file?")
    return root, {}


def unwrap_master(root: dict, *, what: str) -> tuple[dict, dict]:
    """``master.picture.frameArray[0].frame.{metadata, privateMetadata}`` of a white-image TXT."""
    try:
        frame = root["master"]["picture"]["frameArray"][0]["frame"]
        metadata = frame["metadata"]
    except (KeyError, IndexError, TypeError):
        raise MetadataError(f"{what} lacks master.picture.frameArray[0].frame.metadata; "
                            "is it a white-image .TXT from C:\\T1CALIB?") from None
    private = frame.get("privateMetadata", {}) if isinstance(frame, dict) else {}
    if not isinstance(metadata, dict) or not isinstance(private, dict):
        raise MetadataError(f"{what}: frame metadata and privateMetadata must be JSON objects")
    return metadata, private


def master_txt_bytes(metadata: dict, private_metadata: dict) -> bytes:
    """The white-image ``.TXT`` form wrapping frame and private metadata."""
    root = {"master": {"picture": {"frameArray": [{"frame": {"metadata": metadata,
                                                             "privateMetadata": private_metadata}}]}}}
    return json_bytes(root)


def lookup(metadata: Any, path: str, default: Any = None) -> Any:
    """The value at a dotted ``path`` in nested dicts, or ``default`` where any key is missing."""
    node = metadata
    for key in path.split("."):
        if not isinstance(node, dict) or key not in node:
            return default
        node = node[key]
    return node


def image_size(metadata: dict) -> tuple[int, int]:
    """``(width, height)`` from ``image.width/height``.

    Raises
    ------
    MetadataError
        If either is missing or not a positive integer.
    """
    out = []
    for key in ("width", "height"):
        value = lookup(metadata, f"image.{key}")
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
                or value != int(value) or value <= 0:
            raise MetadataError(f"frame metadata field 'image.{key}' is {value!r}, not a positive integer; "
                                "is this an F01 picture's metadata?")
        out.append(int(value))
    return out[0], out[1]


def check_packing(metadata: dict) -> None:
    """Refuse raw data whose metadata declares anything but the F01's packed 12-bit big-endian.

    Fields absent are taken as the F01's. Raises FormatError naming the field otherwise.
    """
    representation = lookup(metadata, "image.representation")
    if representation is not None and representation != "rawPacked":
        raise FormatError(f"image.representation is {representation!r}; only 'rawPacked' (the F01's "
                          "12-bit raw) can be read")
    packing = lookup(metadata, "image.rawDetails.pixelPacking")
    if packing is None:
        return
    if not isinstance(packing, dict):
        raise FormatError(f"image.rawDetails.pixelPacking is {packing!r}, not an object")
    endian = packing.get("endianness", "big")
    bits = packing.get("bitsPerPixel", 12)
    if endian != "big" or bits != 12:
        raise FormatError(f"image.rawDetails.pixelPacking declares {endian!r}-endian {bits!r}-bit pixels; "
                          "only big-endian 12-bit (the F01's) can be read")


def shot_time_s(metadata: dict) -> float | None:
    """When the picture was taken: ``devices.clock.zuluTime`` as seconds since 1970 (UTC), or None
    where the metadata carry no readable clock.

    Examples
    --------
    >>> shot_time_s({"devices": {"clock": {"zuluTime": "2021-06-01T09:00:01.250Z"}}}) % 60
    1.25
    """
    from datetime import datetime, timezone

    text = lookup(metadata, "devices.clock.zuluTime")
    if not isinstance(text, str):
        return None
    try:
        stamp = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        return None
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    return stamp.timestamp()
