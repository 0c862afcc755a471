"""The FastAPI application: ``create_app`` builds it; its lifespan owns workers and watcher.

``create_app(settings)`` is all a deployment needs; tests pass their own settings and,
where they want, a camera, a store or an executor.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from analysis.pipeline.params import PipelineParams
from service.database import Database
from service.deps import ServiceState
from service.disk import DiskGuard
from service.events import EventBus
from service.executors import Executor, make_executor
from service.limits import BodySizeLimit, UrlLengthLimit
from service.metrics import Metrics
from service.problems import install_problem_handlers
from service.queue import JobQueue
from service.routes import (calibrations, camera as camera_routes, events, exposures, health, jobs,
                            metric_calibrations, runs)
from service.runner import JobRunner, RunnerConfig
from service.tracking import RunTracker
from service.settings import Settings, get_settings
from service.metric_calibrations import adopt as adopt_metric
from service.store import Store
from service.watcher import CameraWatcher, open_camera

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"


def package_folder(package: str, *parts: str) -> Path:
    """A folder inside an installed package, found without importing the package."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"the package {package!r} is not installed; run `make setup`")
    return Path(next(iter(spec.submodule_search_locations)), *parts)


# Swagger UI and ReDoc (from fastapi-offline) and plotly.js (from plotly), served by the service:
# the docs and the dashboard must work on a lab network without internet.
DOCS_ASSETS = package_folder("fastapi_offline", "static")
PLOTLY_JS = package_folder("plotly", "package_data") / "plotly.min.js"


def create_app(settings: Settings | None = None, *, camera: Any = None, store: Store | None = None,
               executor: Executor | None = None) -> FastAPI:
    """Build the service.

    Parameters
    ----------
    settings : Settings, optional
        Defaults to the environment (``PLENODUST_*``).
    camera : object, optional
        An open camera to watch instead of opening ``settings.camera``.
    store : Store, optional
        Storage to use instead of one under ``settings.data_dir`` (its database is used too).
    executor : Executor, optional
        Where jobs run, instead of the one ``settings.executor`` names.
    """
    settings = settings or get_settings()
    # Refuse bad pipeline parameters now rather than fail every job later.
    PipelineParams.from_dict(settings.pipeline).validate()
    data_dir = (store.data_dir if store is not None else Path(settings.data_dir)).absolute()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        db = store.db if store is not None else Database(data_dir / "plenodust.sqlite")
        the_store = store or Store(data_dir, db)
        queue = JobQueue(db, capacity=settings.queue_capacity, lease_s=settings.lease_s,
                         max_attempts=settings.max_attempts, retry_after_s=settings.retry_after_s)
        bus = EventBus()
        bus.bind(asyncio.get_running_loop())
        metrics = Metrics()
        the_executor = executor or make_executor(settings.executor, workers=settings.workers,
                                                 warm_up=settings.warm_up)
        disk = DiskGuard(data_dir, settings.min_free_bytes)
        tracker = RunTracker(the_store)
        the_store.on_run_rebuilt = tracker.forget
        runner = JobRunner(queue, the_store, the_executor, bus, metrics,
                           RunnerConfig(slots=settings.workers, heartbeat_s=settings.heartbeat_s,
                                        keep_slices=settings.keep_slices, parameters=settings.pipeline,
                                        raw_retention=settings.raw_retention), guard=disk, tracker=tracker)
        state = ServiceState(settings=settings, db=db, store=the_store, queue=queue, bus=bus, metrics=metrics,
                             executor=the_executor, runner=runner, disk=disk, started_at=time.time(),
                             tracker=tracker)
        if camera is not None or settings.camera != "none":
            opener = (lambda: camera) if camera is not None else (lambda: open_camera(settings.camera))
            state.watcher = CameraWatcher(opener, the_store, queue, bus, metrics,
                                          current_run=lambda: state.current_run, on_queued=runner.wake,
                                          guard=disk,
                                          poll_s=settings.camera_poll_s,
                                          pull_existing=settings.camera_pull_existing)
        app.state.service = state
        if settings.metric_calibration is not None:
            # A calibration given at start joins (or replaces) the service's own for its camera and setting.
            data = await asyncio.to_thread(Path(settings.metric_calibration).read_bytes)
            adopted, _ = await asyncio.to_thread(adopt_metric, the_store.metric_dir, data)
            log.info("target calibration of %s from %s", adopted.camera.describe(), settings.metric_calibration)
        # Jobs whose process died with the last server go back to the queue now.
        for job in await asyncio.to_thread(queue.requeue_expired):
            log.info("job %s back to %s after restart", job.id, job.state)
        tasks: list[asyncio.Task] = []

        async def start_runner() -> None:
            # Jobs wait in the queue until the executor is up (pool warm, cluster reachable).
            started = time.monotonic()
            log.info("starting %d worker(s) (%s): loading the compiled analysis kernels (a few seconds; "
                     "about a minute if they were never compiled: `make setup` compiles them)",
                     settings.workers, settings.executor)
            while True:
                try:
                    await the_executor.start()
                    break
                except Exception as exc:
                    state.executor_error = f"{type(exc).__name__}: {exc}"
                    log.error("executor %s did not start (%s); trying again in 5 s",
                              settings.executor, state.executor_error)
                    await asyncio.sleep(5)
            state.executor_error = None
            log.info("workers ready after %.1f s; processing", time.monotonic() - started)
            runner.start()

        tasks.append(asyncio.create_task(start_runner(), name="runner-start"))
        if state.watcher is not None:
            tasks.append(asyncio.create_task(state.watcher.run(), name="camera-watcher"))
        try:
            yield
        finally:
            bus.close()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await runner.stop()
            await the_executor.close()
            if state.watcher is not None:
                await asyncio.to_thread(state.watcher.close)
            if store is None:
                await asyncio.to_thread(db.close)  # waits for the writes still under way

    app = FastAPI(title="plenodust", version="0.1.0", lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="3D dusty-plasma particle coordinates from single Lytro F01 exposures. "
                              "Errors are application/problem+json; see the README for a Python client "
                              "(service.client).")
    install_problem_handlers(app, data_dir=data_dir)
    app.add_middleware(BodySizeLimit, limit=settings.max_body_bytes,
                       by_path={"/api/v1/calibrations": settings.max_calibration_bytes})
    app.add_middleware(UrlLengthLimit)
    for module in (exposures, jobs, runs, events, camera_routes, metric_calibrations, calibrations, health):
        app.include_router(module.router)

    # Routes under /static/ come before the /static mount, which would take their paths.
    @app.get("/static/vendor/plotly.min.js", include_in_schema=False)
    async def plotly_js() -> FileResponse:
        return FileResponse(PLOTLY_JS, media_type="text/javascript",
                            headers={"Cache-Control": "public, max-age=86400"})

    app.mount("/static/docs", StaticFiles(directory=DOCS_ASSETS), name="docs-assets")
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="plenodust API",
                                   swagger_js_url="/static/docs/swagger-ui-bundle.js",
                                   swagger_css_url="/static/docs/swagger-ui.css",
                                   swagger_favicon_url="/static/favicon.svg")

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url="/openapi.json", title="plenodust API",
                              redoc_js_url="/static/docs/redoc.standalone.js",
                              redoc_favicon_url="/static/favicon.svg", with_google_fonts=False)

    @app.get("/", include_in_schema=False)
    async def dashboard() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon() -> RedirectResponse:
        return RedirectResponse("/static/favicon.svg")

    return app


def app_factory() -> FastAPI:
    """Entry point for ``uvicorn --factory service.app:app_factory``."""
    return create_app()
