"""Packed 12-bit big-endian sensor data: two pixels in three bytes (lytro-f01.md section 1.5)."""

from __future__ import annotations

import numpy as np

from analysis.errors import RawSizeError

F01_WIDTH = 3280
F01_HEIGHT = 3280
F01_RAW_BYTES = F01_WIDTH * F01_HEIGHT * 3 // 2  # 16,137,600


def unpack12(data: bytes | bytearray | memoryview | np.ndarray, *, width: int = F01_WIDTH,
             height: int = F01_HEIGHT) -> np.ndarray:
    """Unpack packed 12-bit big-endian pixels.

    Parameters
    ----------
    data : bytes-like of length ``width * height * 3 / 2``
    width, height : int
        Image size in pixels; ``width * height`` must be even.

    Returns
    -------
    ndarray of shape (height, width), uint16, values 0..4095.

    Raises
    ------
    RawSizeError
        If the byte count does not match the image size.

    Examples
    --------
    >>> unpack12(b"\\x12\\x34\\x56", width=2, height=1).tolist()
    [[291, 1110]]
    """
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    expected = width * height * 3 // 2
    if (width * height) % 2 or buf.size != expected:
        raise RawSizeError(
            f"raw payload has {buf.size} bytes, but a {width}x{height} 12-bit packed image needs "
            f"{expected}; the file is truncated or not a Lytro F01 raw")
    triples = buf.reshape(-1, 3).astype(np.uint16)
    out = np.empty((triples.shape[0], 2), dtype=np.uint16)
    out[:, 0] = (triples[:, 0] << 4) | (triples[:, 1] >> 4)
    out[:, 1] = ((triples[:, 1] & 0x0F) << 8) | triples[:, 2]
    return out.reshape(height, width)


def pack12(image: np.ndarray) -> bytes:
    """Pack an integer image with values 0..4095 into 12-bit big-endian bytes (inverse of `unpack12`).

    Raises
    ------
    RawSizeError
        If the pixel count is odd.
    ValueError
        If a value is outside 0..4095.
    """
    flat = np.asarray(image).reshape(-1)
    if flat.size % 2:
        raise RawSizeError(f"cannot pack an odd number of pixels ({flat.size}) two to three bytes")
    if flat.size and (flat.min() < 0 or flat.max() > 4095):
        raise ValueError("12-bit packing needs values in 0..4095; clip or rescale the image first")
    pairs = flat.astype(np.uint16).reshape(-1, 2)
    out = np.empty((pairs.shape[0], 3), dtype=np.uint8)
    out[:, 0] = pairs[:, 0] >> 4
    out[:, 1] = ((pairs[:, 0] & 0x0F) << 4) | (pairs[:, 1] >> 8)
    out[:, 2] = pairs[:, 1] & 0xFF
    return out.tobytes()
