"""Throughput of a full 16 MB F01 raw through the simulated USB path, against copying the bytes.

What is timed (best of N, after a warm-up):

* ``memcpy``: one copy of the 16,137,600 bytes into a new ``bytes``, the least any
  transfer can cost;
* ``chunked copy``: the copies a bulk transfer implies, chunk by chunk (file bytes -> a
  transfer buffer -> the result) and the final ``bytes``;
* ``driver``: ``Camera.read_file`` over pyusb and the simulated backend: load-file,
  length query, then one CBW / data / CSW exchange per chunk, all through pyusb's own code
  and the byte-level device emulation.

The driver's overhead is printed relative to the chunked copy (the target: under 10 % over
the raw copy of the bytes), and per command (CBW, data, CSW), for several chunk sizes; lyli
uses 64 KiB, the driver's default. A last section splits the cost of one command between
the simulated device, pyusb's own bookkeeping and this driver's code. Peak memory of one read is measured with
tracemalloc.

Run: .venv/bin/python bench/bench_usb.py
"""

from __future__ import annotations

import array
import os
import shutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import best_time  # noqa: E402

import driver  # noqa: E402
from driver import protocol as p  # noqa: E402
from driver.simulated_usb import SimulatedBackend  # noqa: E402

RAW_BYTES = 16_137_600  # 3280 x 3280 pixels, 12 bit packed
CAMERA_PATH = "I:\\DCIM\\100PHOTO\\IMG_0001.RAW"
REPEAT = 11
CHUNKS = (32 * 1024, 64 * 1024, 256 * 1024, 1024 * 1024, 2 * 1024 * 1024)



def chunked_copy(src: bytes, chunk: int, transfer: array.array) -> bytes:
    """The copies of a bulk transfer, with the driver's allocations: device -> buffer -> result.

    ``transfer`` is allocated once, as the driver keeps its transfer buffer between commands.
    """
    view = memoryview(src)
    buffer = memoryview(transfer)
    out = bytearray(len(src))
    result = memoryview(out)
    for offset in range(0, len(src), chunk):
        n = min(chunk, len(src) - offset)
        buffer[:n] = view[offset:offset + n]
        result[offset:offset + n] = buffer[:n]
    return bytes(out)


def interleaved(a, b, repeat: int = REPEAT) -> tuple[float, float]:
    """Best times of ``a`` and ``b``, run alternately so that machine load hits both alike."""
    a(), b()
    ta, tb = [], []
    for _ in range(repeat):
        for fn, times in ((a, ta), (b, tb)):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return min(ta), min(tb)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        raw = os.urandom(RAW_BYTES)
        (folder / "IMG_0001.RAW").write_bytes(raw)
        (folder / "IMG_0001.TXT").write_bytes(b"{}")
        mb = RAW_BYTES / 1e6

        source = bytearray(raw)
        t_memcpy = best_time(lambda: bytes(source), warmup=True)
        print(f"16 MB F01 raw ({RAW_BYTES} bytes), best of {REPEAT}")
        print(f"memcpy                 {t_memcpy * 1e3:8.2f} ms  {mb / t_memcpy:8.0f} MB/s  (into re-used memory; "
              "a transfer's result is fresh memory, whose page faults dominate the copies below)")
        print(f"{'chunk':>8} {'chunked copy':>14} {'driver':>10} {'MB/s':>7} {'vs chunked':>11} "
              f"{'per command':>12}")
        copy_at: dict[int, float] = {}
        for chunk in CHUNKS:
            with driver.open_usb(SimulatedBackend(folder), chunk_size=chunk) as cam:
                assert cam.read_file(CAMERA_PATH) == raw
                transfer = array.array("B", bytes(chunk))
                t_copy, t_driver = interleaved(lambda: chunked_copy(raw, chunk, transfer),
                                               lambda: cam.read_file(CAMERA_PATH))
            copy_at[chunk] = t_copy
            commands = -(-RAW_BYTES // chunk)
            print(f"{chunk // 1024:>6} K {t_copy * 1e3:11.2f} ms {t_driver * 1e3:7.2f} ms {mb / t_driver:7.0f} "
                  f"{(t_driver / t_copy - 1) * 100:+10.1f}% {(t_driver - t_copy) / commands * 1e6:9.1f} us")

        with driver.open_usb(SimulatedBackend(folder)) as cam:
            cam.read_file(CAMERA_PATH)
            tracemalloc.start()
            data = cam.read_file(CAMERA_PATH)
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"peak memory of read_file (64 K chunks): {peak / 1e6:.1f} MB "
                  f"({peak / len(data):.2f} x the file)")
            picture = cam.pictures()[0]
            dest = folder / "pulled"
            tracemalloc.start()
            cam.pull(picture, dest)
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"peak memory of pull (.RAW + .TXT to disk): {peak / 1e6:.1f} MB ({peak / len(data):.2f} x the raw)")

            def plain_copy() -> None:
                shutil.copyfile(folder / "IMG_0001.RAW", dest / "copy.RAW")
                with open(dest / "copy.RAW", "rb+") as f:
                    os.fsync(f.fileno())

            t_copy, t_pull = interleaved(plain_copy, lambda: cam.pull(picture, dest), repeat=5)
            print(f"pull to disk (fsync, rename) {t_pull * 1e3:.1f} ms vs copying the file + fsync "
                  f"{t_copy * 1e3:.1f} ms: {(t_pull / t_copy - 1) * 100:+.1f}%")

        t_dev, t_usb, t_drv = per_command_costs(folder)
        commands = -(-RAW_BYTES // (64 * 1024))
        t_copy = copy_at[64 * 1024]  # measured beside the driver, under the same allocations
        print(f"per command: simulated device {t_dev * 1e6:.1f} us, + pyusb {(t_usb - t_dev) * 1e6:.1f} us, "
              f"+ driver {(t_drv - t_usb) * 1e6:.1f} us")
        print(f"the driver's own share for a 16 MB raw at 64 K chunks ({commands} commands): "
              f"{(t_drv - t_usb) * commands * 1e3:.2f} ms = {(t_drv - t_usb) * commands / t_copy * 100:+.1f}% "
              "over the chunked copy of the table")


def per_command_costs(folder: Path, n: int = 3000) -> tuple[float, float, float]:
    """Seconds per command (a 4-byte battery query: CBW, data, CSW) at three depths.

    Returns (simulated device alone, pyusb + device, driver + pyusb + device).
    """
    backend = SimulatedBackend(folder)
    with driver.open_usb(backend) as cam:
        dev, transport = cam.transport.device, cam.transport
        handle = dev._ctx.handle
        cdb = p.cdb_query_battery()
        data, csw = array.array("B", bytes(4)), array.array("B", bytes(13))
        # The same CBW bytes at every depth (pyusb converts to an array itself).
        cbws = [p.encode_cbw(cdb, tag=i, data_length=4, direction_in=True) for i in range(n)]
        cbw_arrays = [array.array("B", c) for c in cbws]

        def device_only() -> None:
            for cbw in cbw_arrays:
                backend.bulk_write(handle, p.EP_OUT, 0, cbw, 5000)
                backend.bulk_read(handle, p.EP_IN, 0, data, 5000)
                backend.bulk_read(handle, p.EP_IN, 0, csw, 5000)

        def through_pyusb() -> None:
            for cbw in cbws:
                dev.write(p.EP_OUT, cbw, 5000)
                dev.read(p.EP_IN, data, 5000)
                dev.read(p.EP_IN, csw, 5000)

        def through_driver() -> None:
            for _ in range(n):
                transport.execute(cdb, data_in_length=4)

        times: list[list[float]] = [[], [], []]
        for _ in range(7):  # interleaved, best of 7
            for k, fn in enumerate((device_only, through_pyusb, through_driver)):
                t0 = time.perf_counter()
                fn()
                times[k].append((time.perf_counter() - t0) / n)
        return min(times[0]), min(times[1]), min(times[2])


if __name__ == "__main__":
    main()
