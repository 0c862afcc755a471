"""Arrays of an uncompressed ``.npz`` file mapped into memory instead of read, and their pages
given back once read.

A mapped array costs memory only for the pages that are read (and those stay in the system's file
cache when given back: :func:`release_pages`). What the pipeline caches on disk (the calibration's
devignetting map, the look-up tables with their refocus normalisations) is written uncompressed by
``np.savez``, and much of it is read for one step only, or not at all for a given exposure.
"""

from __future__ import annotations

import math
import os
import mmap
import struct
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import BinaryIO

import numpy as np


#: Members' data start at a multiple of this in the file (numpy's own header alignment), so that
#: mapped arrays are aligned: numba compiles unaligned arrays as another, slower type.
ALIGN = 64
#: Extra-field id of the padding before a member's data (the one Android's zipalign uses).
_PADDING_ID = 0xD935


def save_aligned(fh: BinaryIO, arrays: Mapping[str, np.ndarray], *, release: bool = False) -> None:
    """Write ``arrays`` to the open file ``fh`` as an uncompressed ``.npz`` (``np.load`` reads it)
    whose members' data start at multiples of :data:`ALIGN`, ready for :func:`map_members`.

    ``release``: give back the pages of file-mapped arrays once written (:func:`release_pages`),
    so that writing what was mapped and not read does not bring it all into memory."""
    with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            value = np.asanyarray(value)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_STORED
            # Local header: 30 bytes, the name, our padding record, the 20-byte zip64 record
            # (forced, so that its length is known); numpy pads its own header to ALIGN.
            start = fh.tell() + 30 + len(info.filename.encode()) + 20
            pad = -start % ALIGN
            pad += ALIGN if 0 < pad < 4 else 0  # a record needs its 4-byte id and length
            info.extra = struct.pack("<HH", _PADDING_ID, pad - 4) + bytes(pad - 4) if pad else b""
            with zf.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, value, allow_pickle=False)
            if release:
                release_pages(value)


def map_members(path: str | Path, names: Iterable[str], *, mode: str = "r") -> dict[str, np.ndarray]:
    """Arrays over one memory map of an ``.npz`` file, for those of the ``.npy`` members ``names``
    (without ``.npy``) that it stores uncompressed; others (compressed, missing, objects) are left out.

    ``mode``: ``"r"`` read-only arrays, ``"c"`` copy-on-write (writable, never written to the file:
    numba compiles read-only arrays as another type). One map, so one file descriptor, per call.
    """
    path = Path(path)
    places: dict[str, tuple[int, tuple[int, ...], bool, np.dtype]] = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        for name in names:
            try:
                info = zf.getinfo(name + ".npy")
            except KeyError:
                continue
            if info.compress_type != zipfile.ZIP_STORED:
                continue
            fh.seek(info.header_offset)
            local = fh.read(30)  # the zip local file header: its name and extra field lengths at 26
            if len(local) < 30 or local[:4] != b"PK\x03\x04":
                continue
            name_len, extra_len = struct.unpack("<HH", local[26:30])
            fh.seek(info.header_offset + 30 + name_len + extra_len)
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(fh)
            offset = fh.tell()
            if not dtype.hasobject and offset + dtype.itemsize * math.prod(shape) <= size:
                places[name] = (offset, shape, fortran, dtype)
        if not places:
            return {}
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY if mode == "c" else mmap.ACCESS_READ)
    whole = np.frombuffer(mm, dtype=np.uint8)
    out = {}
    for name, (offset, shape, fortran, dtype) in places.items():
        n = dtype.itemsize * math.prod(shape)
        out[name] = whole[offset:offset + n].view(dtype).reshape(shape, order="F" if fortran else "C")
    return out


def _mapping(array: np.ndarray) -> mmap.mmap | None:
    base = array
    while base is not None and not isinstance(base, mmap.mmap):
        # np.frombuffer's arrays hold a memoryview of the map
        base = base.obj if isinstance(base, memoryview) else getattr(base, "base", None)
    return base


def is_mapped(array: np.ndarray) -> bool:
    """Whether the array lies in a memory-mapped file."""
    return _mapping(array) is not None


def release_pages(array: np.ndarray) -> None:
    """Let the system drop the pages of a file-mapped array from this process's memory once it has
    been read: they stay in the file cache and are read back if the array is used again. Nothing
    for arrays in memory. (Copy-on-write maps: what was written to the array is lost; the tables
    mapped so are never written to.)"""
    base = _mapping(array)
    if base is None or not hasattr(mmap, "MADV_DONTNEED"):
        return
    try:
        start, length = 0, len(base)
        if array.flags.c_contiguous or array.flags.f_contiguous:  # only the array's own pages
            offset = array.ctypes.data - np.frombuffer(base, dtype=np.uint8, count=1).ctypes.data
            start = max(0, offset // mmap.PAGESIZE * mmap.PAGESIZE)
            length = min(len(base), offset + array.nbytes) - start
        if length > 0:
            base.madvise(mmap.MADV_DONTNEED, start, length)
    except (OSError, ValueError):  # a closed map, or a system that refuses: only memory is at stake
        pass
