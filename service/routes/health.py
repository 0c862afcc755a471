"""``/healthz``, ``/readyz`` and ``/metrics``."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter
from fastapi.responses import JSONResponse, PlainTextResponse

from service.deps import State
from service.models import Health, Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="The process is alive", response_model=Health)
async def healthz() -> dict:
    return {"status": "ok"}


@router.get("/readyz", summary="Database writable, workers warm, free space on the data disk, camera state",
            response_model=Readiness, responses={503: {"model": Readiness, "description": "not ready"}})
async def readyz(state: State) -> JSONResponse:
    writable = await asyncio.to_thread(state.db.writable)
    disk = await asyncio.to_thread(state.disk.status)
    warm = state.executor.warm
    camera = state.watcher.status() if state.watcher is not None else {"state": "none"}
    camera_ok = camera["state"] in ("none", "connected", "idle")
    ready = writable and warm and disk["ok"]
    body = {"ready": ready, "database": "writable" if writable else "not writable",
            "workers": "warm" if warm else "warming", "executor": state.executor.name,
            "camera": camera["state"], "camera_ok": camera_ok, "disk": disk,
            "uptime_s": round(time.time() - state.started_at, 1)}
    if state.executor_error:
        body["executor_error"] = state.executor_error
    return JSONResponse(body, status_code=200 if ready else 503)


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics")
async def metrics(state: State) -> PlainTextResponse:
    depth = await asyncio.to_thread(state.queue.depth)
    free = await asyncio.to_thread(state.disk.free_bytes)
    waiting = await asyncio.to_thread(state.queue.waiting, "space")
    gauges = {
        "plenodust_data_free_bytes": ("Free space on the data folder's disk.", {(): float(free)}),
        "plenodust_data_min_free_bytes": ("Free space the service keeps (PLENODUST_MIN_FREE_BYTES).",
                                          {(): float(state.disk.margin_bytes)}),
        "plenodust_jobs_waiting_for_space": ("Failed jobs that run again once space returns.", {(): float(waiting)}),
        "plenodust_queue_depth": ("Jobs by state.", {(("state", s),): float(n) for s, n in depth.items()}),
        "plenodust_queue_capacity": ("Most jobs queued or running at once.", {(): float(state.queue.capacity)}),
        "plenodust_workers_warm": ("1 when the workers are warm.", {(): 1.0 if state.executor.warm else 0.0}),
        "plenodust_event_subscribers": ("Open event streams.", {(): float(state.bus.subscribers)}),
    }
    return PlainTextResponse(state.metrics.render(gauges), media_type="text/plain; version=0.0.4")
