"""12-bit packing against miloush's worked examples (lytro-f01.md 1.5) and exact round trips."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.errors import RawSizeError
from analysis.formats.raw12 import F01_RAW_BYTES, pack12, unpack12


def test_documented_examples_unpack():
    assert unpack12(b"\x12\x34\x56", width=2, height=1).tolist() == [[0x123, 0x456]]
    # "FF F0 00" is white then black.
    assert unpack12(b"\xff\xf0\x00", width=2, height=1).tolist() == [[4095, 0]]


def test_documented_examples_pack():
    assert pack12(np.array([[0x123, 0x456]], dtype=np.uint16)) == b"\x12\x34\x56"
    assert pack12(np.array([[4095, 0]], dtype=np.uint16)) == b"\xff\xf0\x00"


def test_random_bytes_round_trip_exactly():
    rng = np.random.default_rng(1)
    data = rng.integers(0, 256, size=48 * 32 * 3 // 2, dtype=np.uint8).tobytes()
    image = unpack12(data, width=48, height=32)
    assert image.shape == (32, 48) and image.dtype == np.uint16
    assert image.max() <= 4095
    assert pack12(image) == data


def test_random_image_round_trips_exactly():
    rng = np.random.default_rng(2)
    image = rng.integers(0, 4096, size=(16, 20), dtype=np.uint16)
    assert np.array_equal(unpack12(pack12(image), width=20, height=16), image)


def test_row_major_order():
    image = np.arange(12, dtype=np.uint16).reshape(3, 4)
    packed = pack12(image)
    # Pixels (0,0) and (0,1) share the first three bytes.
    assert packed[:3] == bytes([0x00, 0x00, 0x01])
    assert np.array_equal(unpack12(packed, width=4, height=3), image)


def test_f01_size_constant():
    assert F01_RAW_BYTES == 16_137_600


@pytest.mark.parametrize("size", [0, 2, 3 * 2 * 2 // 2 * 3 - 1, 12 * 12 * 3 // 2 + 1])
def test_wrong_size_raises(size):
    with pytest.raises(RawSizeError, match="12-bit"):
        unpack12(b"\x00" * size, width=12, height=12)


def test_odd_pixel_count_cannot_pack():
    with pytest.raises(RawSizeError):
        pack12(np.zeros((3, 3), dtype=np.uint16))


def test_out_of_range_cannot_pack():
    with pytest.raises(ValueError, match="0..4095"):
        pack12(np.array([[4096, 0]]))
