"""`plenodust camera info|list|pull|calibration|watch`: talk to a Lytro F01.

The camera is reached over USB (default), Wi-Fi (``--wifi HOST[:PORT]``), or simulated
from a folder (``--simulated DIR``, e.g. one written by ``plenodust simulate``).
Exit status: 0 on success, 1 when the camera fails or cannot be found.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path
from typing import Any

import driver
from driver.protocol import Picture

EXIT_OK, EXIT_CAMERA = 0, 1


def register(subparsers: argparse._SubParsersAction) -> None:
    connection = argparse.ArgumentParser(add_help=False)
    how = connection.add_mutually_exclusive_group()
    how.add_argument("--usb", action="store_true", help="the camera on USB (default)")
    how.add_argument("--wifi", metavar="HOST[:PORT]", help="the camera on Wi-Fi (its address is 10.100.1.1)")
    how.add_argument("--simulated", metavar="DIR", type=Path, help="a simulated camera serving the files in DIR")
    connection.add_argument("--chunk-size", type=int, default=64 * 1024, metavar="BYTES",
                            help="bytes per download command (default 65536)")
    connection.add_argument("--retries", type=int, default=3, help="attempts after a failed command (default 3)")
    connection.add_argument("--quiet", action="store_true", help="no progress bars")

    parser = subparsers.add_parser("camera", help="talk to a Lytro F01: info, list, pull, calibration, watch",
                                   description=__doc__.split("\n\n")[1])
    commands = parser.add_subparsers(dest="camera_command", metavar="ACTION", required=True)

    p = commands.add_parser("info", parents=[connection], help="hardware info, battery and clock as JSON")
    p.set_defaults(func=_guard(_info))

    p = commands.add_parser("list", parents=[connection], help="the pictures on the camera")
    p.add_argument("--json", action="store_true", help="one JSON object per picture")
    p.set_defaults(func=_guard(_list))

    p = commands.add_parser("pull", parents=[connection], help="copy pictures (.RAW, .TXT, .128) to a folder")
    p.add_argument("pictures", nargs="*", metavar="PICTURE",
                   help="names (IMG_0001) or ids (sha1-...); default: all")
    p.add_argument("--latest", action="store_true", help="only the newest picture")
    p.add_argument("--out", type=Path, default=Path("."), help="destination folder (default: here)")
    p.set_defaults(func=_guard(_pull))

    p = commands.add_parser("calibration", parents=[connection],
                            help=r"copy the white images (C:\T1CALIB\MOD_*) to a folder")
    p.add_argument("--out", type=Path, default=Path("calibration"), help="destination (default ./calibration)")
    p.set_defaults(func=_guard(_calibration))

    p = commands.add_parser("watch", parents=[connection], help="pull each new picture as it is taken")
    p.add_argument("--out", type=Path, default=Path("."), help="destination folder (default: here)")
    p.add_argument("--poll", type=float, default=2.0, metavar="SECONDS", help="picture-list poll interval")
    p.add_argument("--count", type=int, default=None, help="stop after this many pictures")
    p.set_defaults(func=_guard(_watch))


def open_camera(args: argparse.Namespace) -> driver.Camera:
    """The camera the connection options name."""
    settings = {"chunk_size": args.chunk_size, "retries": args.retries}
    if args.simulated is not None:
        return driver.open_simulated(args.simulated, **settings)
    if args.wifi:
        host, _, port = args.wifi.partition(":")
        return driver.open_wifi(host, int(port) if port else 5678, **settings)
    return driver.open_usb(**settings)


def _guard(command):
    def run(args: argparse.Namespace) -> int:
        try:
            with open_camera(args) as camera:
                return command(camera, args)
        except driver.CameraError as exc:
            print(f"plenodust camera {args.camera_command}: {exc}", file=sys.stderr)
            return EXIT_CAMERA
        except KeyboardInterrupt:  # Ctrl-C ends `watch`; files are written whole or not at all
            return 130
    return run


class _Bars:
    """One tqdm bar per file, fed by the driver's progress callback."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.bar: Any = None
        self.path: str | None = None

    def __call__(self, path: str, done: int, total: int) -> None:
        if self.quiet:
            return
        if path != self.path:
            from tqdm import tqdm  # only here: `camera info` and `list` need no bars

            self.close()
            self.path = path
            self.bar = tqdm(total=total, desc=path.rsplit("\\", 1)[-1], unit="B", unit_scale=True,
                            unit_divisor=1024, leave=False, file=sys.stderr, disable=None)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _info(camera: driver.Camera, args: argparse.Namespace) -> int:
    info = camera.info()
    report = {"manufacturer": info.manufacturer, "serial": info.serial, "build": info.build,
              "software": info.software, "battery_percent": round(camera.battery(), 1),
              "time": camera.time().isoformat()}
    json.dump(report, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return EXIT_OK


def _record(pic: Picture) -> dict:
    return {"name": pic.name, "id": pic.id, "taken": pic.taken.isoformat(), "path": pic.path,
            "starred": pic.starred, "rotation_degrees": pic.rotation_degrees}


def _list(camera: driver.Camera, args: argparse.Namespace) -> int:
    for pic in camera.pictures():
        if args.json:
            print(json.dumps(_record(pic)))
        else:
            print(f"{pic.name}  {pic.taken:%Y-%m-%d %H:%M:%S}Z  {pic.id}  {pic.path}")
    return EXIT_OK


def _pull(camera: driver.Camera, args: argparse.Namespace) -> int:
    pictures = camera.pictures()
    if args.pictures:
        wanted = set(args.pictures)
        chosen = [pic for pic in pictures if pic.name in wanted or pic.id in wanted]
        missing = wanted - {pic.name for pic in chosen} - {pic.id for pic in chosen}
        if missing:
            print(f"plenodust camera pull: not on the camera: {', '.join(sorted(missing))} "
                  "(see `plenodust camera list`)", file=sys.stderr)
            return EXIT_CAMERA
    else:
        chosen = pictures[-1:] if args.latest else pictures
    bars = _Bars(args.quiet)
    try:
        for pic in chosen:
            for path in camera.pull(pic, args.out, progress=bars):
                print(path)
    finally:
        bars.close()
    return EXIT_OK


def _calibration(camera: driver.Camera, args: argparse.Namespace) -> int:
    bars = _Bars(args.quiet)
    try:
        written = camera.pull_calibration(args.out, progress=bars)
    finally:
        bars.close()
    for path in written:
        print(path)
    if not written:
        print("plenodust camera calibration: the camera has no white images", file=sys.stderr)
        return EXIT_CAMERA
    return EXIT_OK


def _watch(camera: driver.Camera, args: argparse.Namespace) -> int:
    stop = threading.Event()
    bars = _Bars(args.quiet)
    pulled = 0
    try:
        for pic in camera.watch(poll_s=args.poll, stop=stop):
            for path in camera.pull(pic, args.out, progress=bars):
                print(path, flush=True)
            pulled += 1
            if args.count is not None and pulled >= args.count:
                stop.set()
    finally:
        bars.close()
    return EXIT_OK
