"""Speed and memory of the file formats on a full-size F01 exposure (3280 x 3280, 16 MB raw).

Prints seconds (best of N) and, as a machine-independent figure, each time as a multiple of
one SHA-1 pass over the 16 MB raw (the least any verified read must do). Peak memory is
measured with tracemalloc (NumPy reports its buffers there) beyond the inputs.

Run: .venv/bin/python bench/bench_formats.py
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import best_time  # noqa: E402

from analysis.formats.exposure import (Exposure, exposure_from_lfp_bytes, lfp_bytes, read_exposure,
    write_lfp, write_raw_pair)
from analysis.formats.file_report import inspect_file  # noqa: E402
from analysis.formats.lfp import read_container  # noqa: E402
from analysis.formats.raw12 import pack12, unpack12  # noqa: E402





def peak_mib(fn) -> float:
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def main() -> None:
    meta = json.loads((ROOT.parent / "shared" / "fixtures" / "real" / "f01-frame-metadata.json").read_text())
    image = np.random.default_rng(0).integers(0, 4096, size=(3280, 3280), dtype=np.uint16)
    exp = Exposure(image=image, metadata=meta, private_metadata={"camera": {"serialNumber": "A0"}})
    raw = pack12(image)
    blob = lfp_bytes(exp)
    base = best_time(lambda: hashlib.sha1(raw).digest())
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        lfp_path = write_lfp(exp, tmp / "IMG_0001.lfp")
        raw_path, _ = write_raw_pair(exp, tmp / "IMG_0001.RAW")
        cases = {
            "unpack12 (16 MB -> uint16)": lambda: unpack12(raw),
            "pack12": lambda: pack12(image),
            "read_container (verify SHA-1)": lambda: read_container(blob),
            "exposure_from_lfp_bytes": lambda: exposure_from_lfp_bytes(blob),
            "read_exposure .lfp (from disk)": lambda: read_exposure(lfp_path),
            "read_exposure .RAW + .TXT": lambda: read_exposure(raw_path),
            "lfp_bytes (pack + SHA-1s)": lambda: lfp_bytes(exp),
            "write_lfp (atomic, fsync)": lambda: write_lfp(exp, tmp / "out.lfp"),
            "inspect_file .lfp": lambda: inspect_file(lfp_path),
        }
        print(f"baseline: one SHA-1 of 16 MB = {base * 1e3:.1f} ms")
        print(f"{'operation':34s} {'ms':>8s} {'x SHA-1':>8s} {'peak MiB':>9s}")
        for name, fn in cases.items():
            t = best_time(fn)
            print(f"{name:34s} {t * 1e3:8.1f} {t / base:8.1f} {peak_mib(fn):9.1f}")


if __name__ == "__main__":
    main()
