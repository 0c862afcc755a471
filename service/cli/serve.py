"""``plenodust serve``: run the lab service (REST API, queue, workers, camera watcher, dashboard)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve", help="run the lab service",
        description="Serve the REST API under /api/v1 (OpenAPI at /docs), the dashboard at /, and process "
                    "every uploaded or pulled exposure. Options override PLENODUST_* variables.")
    parser.add_argument("--host", default=None, help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="port (default 8000; 0 picks a free one)")
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="data folder: SQLite, raw exposures, HDF5 results (default ./plenodust-data)")
    parser.add_argument("--camera", default=None, metavar="usb|wifi:HOST[:PORT]|simulated:DIR|none",
                        help="camera to watch for new shots (default none)")
    parser.add_argument("--executor", default=None, metavar="local|dask://HOST:PORT",
                        help="where jobs run (default: a local warm process pool)")
    parser.add_argument("--workers", type=int, default=None, metavar="N", help="jobs at once (default 1)")
    parser.add_argument("--run", default=None, metavar="NAME", help="run new shots are filed under")
    parser.add_argument("--queue-capacity", type=int, default=None, metavar="N",
                        help="jobs waiting or running before uploads get 503 (default 64)")
    parser.add_argument("--metric-calibration", type=Path, default=None, metavar="FILE",
                        help="a target calibration (plenodust calibrate-target) for X, Y, Z in mm; the service keeps "
                             "it with those uploaded to /api/v1/calibrations/metric")
    parser.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace):
    """Settings from the environment, with the command line's options on top."""
    from service.settings import Settings

    overrides = {"host": args.host, "port": args.port, "data_dir": args.data, "camera": args.camera,
                 "executor": args.executor, "workers": args.workers, "run": args.run,
                 "queue_capacity": args.queue_capacity, "metric_calibration": args.metric_calibration}
    return Settings(**{k: v for k, v in overrides.items() if v is not None})


def serve(settings, *, camera=None, announce: str | None = None) -> int:
    """Run uvicorn with the app until interrupted."""
    import uvicorn

    from service.app import create_app

    from service.limits import HEAD_LIMIT_BYTES, http_protocol_class

    # The service says what it does at start (workers warming up, ready) at the log level asked.
    logging.getLogger("service").setLevel(settings.log_level.upper())
    app = create_app(settings, camera=camera)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=settings.log_level,
                            # Open event streams must not hold a shutdown for long.
                            timeout_graceful_shutdown=3,
                            # h11, answering a too-long URL with 414 rather than a reset connection.
                            http=http_protocol_class(), h11_max_incomplete_event_size=2 * HEAD_LIMIT_BYTES)
    server = uvicorn.Server(config)
    if announce:
        print(announce, flush=True)
    server.run()
    return 0


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    try:
        settings = settings_from_args(args)
    except ValidationError as exc:
        for error in exc.errors():
            print(f"plenodust serve: {'.'.join(map(str, error['loc']))}: {error['msg']}")
        return 2
    from analysis.errors import ParameterError

    try:
        from analysis.pipeline.params import PipelineParams

        PipelineParams.from_dict(settings.pipeline).validate()
    except ParameterError as exc:
        print(f"plenodust serve: PLENODUST_PIPELINE: {exc}")
        return 2
    if settings.metric_calibration is not None:
        from analysis.calibration.metric_files import read_metric_calibration
        from analysis.errors import MetricCalibrationError

        try:
            read_metric_calibration(settings.metric_calibration)
        except (MetricCalibrationError, OSError) as exc:
            print(f"plenodust serve: --metric-calibration: {exc}")
            return 2
    return serve(settings, announce=f"plenodust: dashboard at http://{settings.host}:{settings.port}/ "
                                     f"(API docs at /docs), data in {settings.data_dir}")
