"""``plenodust demo`` (``make run``): the service with a simulated camera that keeps shooting."""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo", help="run the service with a simulated camera that takes a shot every few seconds",
        description="Start the lab service on 127.0.0.1:8000 with a simulated F01 whose folder gets a new "
                    "simulated shot of a dust cluster every few seconds; open the printed URL to watch the "
                    "clusters appear on the dashboard.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="data folder (default: a new temporary folder)")
    parser.add_argument("--every", type=float, default=4.0, metavar="SECONDS", help="time between shots")
    parser.add_argument("--size", type=int, default=1024, metavar="PX",
                        help="simulated sensor crop (multiple of 4; 3280 = full F01 frame)")
    parser.add_argument("--scenario", default="ball", choices=["ball", "tilted-layer", "shadowing"])
    parser.add_argument("--workers", type=int, default=1)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    print(f"plenodust demo: dashboard at http://{args.host}:{args.port}/  (API docs at /docs; Ctrl-C stops)",
          flush=True)
    from service.cli.serve import serve
    from service.demo_shots import DemoShots
    from service.settings import Settings

    data = args.data or Path(tempfile.mkdtemp(prefix="plenodust-demo-"))
    camera_dir = data / "simulated-camera"
    print(f"plenodust demo: data in {data}; preparing the simulated camera ...", flush=True)
    shots = DemoShots(camera_dir, scenario=args.scenario, size=args.size)
    if not (camera_dir / "calibration").is_dir():
        shots.prepare()
    settings = Settings(host=args.host, port=args.port, data_dir=data / "service", camera=f"simulated:{camera_dir}",
                        workers=args.workers, run="demo", camera_poll_s=1.0,
                        camera_pull_existing=True)
    shots.start(args.every)
    try:
        return serve(settings)
    finally:
        shots.stop()
