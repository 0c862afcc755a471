"""Uncompressed .npz files whose members are memory mapped, aligned, and give their pages back."""

from __future__ import annotations

import numpy as np

from analysis.formats.mapped_npz import ALIGN, is_mapped, map_members, release_pages, save_aligned


def test_aligned_members_map_and_read_back_after_release(tmp_path):
    arrays = {f"a{k}": np.arange(k * 1000 + 7, dtype=dtype)
              for k, dtype in enumerate([np.float32, np.int64, np.uint8, np.float64, np.int32])}
    arrays["empty"] = np.empty(0, np.float32)
    arrays["matrix"] = np.arange(12.0).reshape(3, 4)
    path = tmp_path / "x.npz"
    with open(path, "wb") as fh:
        save_aligned(fh, arrays)
    with np.load(path) as data:  # an ordinary .npz
        for name, value in arrays.items():
            np.testing.assert_array_equal(data[name], value)
    mapped = map_members(path, [*arrays, "missing"], mode="c")
    assert sorted(mapped) == sorted(arrays)
    for name, value in mapped.items():
        assert value.dtype == arrays[name].dtype and value.shape == arrays[name].shape
        assert value.flags.writeable and value.flags.c_contiguous
        if value.size:
            assert is_mapped(value) and value.ctypes.data % ALIGN == 0, name
        release_pages(value)
        np.testing.assert_array_equal(value, arrays[name])
    assert not map_members(path, ["a0"])["a0"].flags.writeable  # mode "r"


def test_compressed_members_are_left_to_np_load(tmp_path):
    path = tmp_path / "z.npz"
    np.savez_compressed(path, a=np.arange(10))
    assert map_members(path, ["a"]) == {}
