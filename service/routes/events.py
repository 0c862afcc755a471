"""``/api/v1/events``: server-sent events for job state changes and new results."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Header
from fastapi.sse import EventSourceResponse, ServerSentEvent

from service.deps import State

router = APIRouter(prefix="/api/v1", tags=["events"])


@router.get("/events", response_class=EventSourceResponse,
            summary="Server-sent events: 'job' (state, progress), 'result' (new particles), 'tracks' (shots linked), 'camera', 'run'")
async def events(state: State,
                 last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None,
                 ) -> AsyncIterator[ServerSentEvent]:
    # A first event tells the client the stream is live (and lets tests wait for it).
    yield ServerSentEvent(event="hello", raw_data=json.dumps({"run": state.current_run}))
    # A browser reconnecting sends the last id it saw: replay what it missed since.
    after = int(last_event_id) if last_event_id and last_event_id.isdigit() else None
    async for event in state.bus.subscribe(after=after):
        yield ServerSentEvent(event=event.kind, id=str(event.id), raw_data=json.dumps(event.data))
