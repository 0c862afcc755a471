"""``plenodust demo`` (``make run``): the service with a simulated camera that keeps shooting.

The demo is bounded: the simulated card keeps the newest ``--keep`` shots and the service the raw
files of as many exposures (``PLENODUST_RAW_RETENTION``); a temporary data folder is removed on
exit unless ``--keep-data`` (a folder given with ``--data`` is always kept).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

# The simulated cluster's refocus range is known (the simulator's ball around the focus), so the
# demo gives it rather than have each job survey the exposure for it: the shots' processing time
# then does not depend on the survey (which once took 10-20 s a shot on 2 cores, longer than the
# time between shots). Drop this to show the survey in the demo.
DEMO_PIPELINE = {"alpha_min": 0.987, "alpha_max": 1.013}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo", help="run the service with a simulated camera that takes a shot every few seconds",
        description="Start the lab service on 127.0.0.1:8000 with a simulated F01 that takes a shot of a dust "
                    "cluster every --every seconds (on a fixed clock; POST /api/v1/camera/shots takes one at "
                    "once); open the printed URL to watch the clusters appear on the dashboard. The newest "
                    "--keep shots are kept; a temporary data folder is removed on exit.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="data folder, kept on exit (default: a new temporary folder, removed on exit)")
    parser.add_argument("--keep-data", action="store_true", help="keep the temporary data folder on exit")
    parser.add_argument("--every", type=float, default=4.0, metavar="SECONDS",
                        help="time between shots (default 4; 0: only when asked, POST /api/v1/camera/shots)")
    parser.add_argument("--keep", type=int, default=200, metavar="N",
                        help="shots (and raw exposures) kept; older ones are deleted (default 200)")
    parser.add_argument("--size", type=int, default=1024, metavar="PX",
                        help="simulated sensor crop (multiple of 4; 3280 = full F01 frame)")
    parser.add_argument("--scenario", default="ball", choices=["ball", "tilted-layer", "shadowing"])
    parser.add_argument("--workers", type=int, default=1)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    print(f"plenodust demo: dashboard at http://{args.host}:{args.port}/  (API docs at /docs; Ctrl-C stops)",
          flush=True)
    if args.every < 0 or args.keep < 1:
        print("plenodust demo: --every must be 0 or more and --keep at least 1")
        return 2
    import driver
    from service.cli.serve import serve
    from service.demo_shots import DemoShots
    from service.settings import Settings

    temporary = args.data is None
    data = args.data or Path(tempfile.mkdtemp(prefix="plenodust-demo-"))
    camera_dir = data / "simulated-camera"
    try:
        print(f"plenodust demo: data in {data}"
              + (" (removed on exit; --keep-data keeps it)" if temporary and not args.keep_data else "")
              + "; rendering the simulated camera's white images and first shot ...", flush=True)
        shots = DemoShots(camera_dir, scenario=args.scenario, size=args.size, keep=args.keep,
                          every_s=args.every)
        if not (camera_dir / "calibration").is_dir():
            shots.prepare()
        every = f"a shot every {args.every:g} s" if args.every else "shots on request only"
        print(f"plenodust demo: simulated camera {shots.serial}, {every} (POST /api/v1/camera/shots takes "
              f"one now); keeping the newest {args.keep}", flush=True)
        settings = Settings(host=args.host, port=args.port, data_dir=data / "service", camera=f"simulated:{camera_dir}",
                            workers=args.workers, run="demo", camera_poll_s=1.0, camera_pull_existing=True,
                            raw_retention=args.keep, pipeline=DEMO_PIPELINE)
        camera = driver.open_simulated(camera_dir, shutter=shots.shutter, serial=shots.serial)
        if args.every:
            shots.start(args.every)
        try:
            return serve(settings, camera=camera)
        finally:
            shots.stop()
    finally:
        if temporary and not args.keep_data:
            shutil.rmtree(data, ignore_errors=True)
            print(f"plenodust demo: removed {data}", flush=True)
        else:
            print(f"plenodust demo: data kept in {data}", flush=True)
