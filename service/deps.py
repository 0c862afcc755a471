"""What routes depend on: the service's parts, and the API-key check for mutating routes."""

from __future__ import annotations

import asyncio
import hmac
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import Depends, Request

from service.database import Database
from service.disk import DiskGuard
from service.events import EventBus
from service.executors import Executor
from service.metrics import Metrics
from service.problems import Problem
from service.queue import JobQueue
from service.runner import JobRunner
from service.settings import Settings
from service.store import Store


@dataclass
class ServiceState:
    """The parts of a running service, built by the app's lifespan."""

    settings: Settings
    db: Database
    store: Store
    queue: JobQueue
    bus: EventBus
    metrics: Metrics
    executor: Executor
    runner: JobRunner
    disk: DiskGuard
    watcher: Any = None          # service.watcher.CameraWatcher when a camera is configured
    tracker: Any = None          # service.tracking.RunTracker: links each run's shots as they arrive
    started_at: float = 0.0
    executor_error: str | None = None
    # Uploads read and decoded at once (a full F01 frame takes ~100 MB while it is checked).
    upload_slots: asyncio.Semaphore = field(default_factory=lambda: asyncio.Semaphore(3))

    @property
    def current_run(self) -> str:
        return self.db.get_value("current_run") or self.settings.run


def get_state(request: Request) -> ServiceState:
    return request.app.state.service


State = Annotated[ServiceState, Depends(get_state)]


def require_api_key(request: Request, state: State) -> None:
    """Refuse a mutating request without the right ``Authorization: Bearer`` key (when one is set)."""
    key = state.settings.api_key
    if key is None:
        return
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(token.strip().encode(),
                                                             key.get_secret_value().encode()):
        raise Problem(401, "Unauthorized",
                      "this route needs the header 'Authorization: Bearer <key>' with the service's "
                      "API key (PLENODUST_API_KEY)", kind="unauthorized",
                      headers={"WWW-Authenticate": 'Bearer realm="plenodust"'})


ApiKey = Depends(require_api_key)
