"""An in-process event bus feeding the server-sent event stream (``/api/v1/events``)."""

from __future__ import annotations

import asyncio
import collections
import itertools
import threading
from collections.abc import AsyncIterator
from dataclasses import dataclass


@dataclass(frozen=True)
class Event:
    """One event: ``kind`` names it (``job``, ``result``, ``camera``), ``data`` is JSON-able."""

    id: int
    kind: str
    data: dict


class EventBus:
    """Fan-out of events to every connected subscriber.

    :meth:`publish` may be called from any thread; subscribers are async iterators on the
    loop the bus was bound to. A subscriber that falls behind by ``backlog`` events loses
    the oldest ones rather than holding memory for ever.
    """

    def __init__(self, *, backlog: int = 1000, history: int = 500) -> None:
        self.backlog = backlog
        # Recent events, replayed to a client that reconnects with Last-Event-ID.
        self._history: collections.deque[Event] = collections.deque(maxlen=history)
        self._ids = itertools.count(1)
        self._subscribers: set[asyncio.Queue[Event | None]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()
        self.closed = False

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self.closed = False

    def publish(self, kind: str, data: dict) -> None:
        """Send an event to every subscriber (thread-safe, never blocks)."""
        with self._lock:
            event = Event(next(self._ids), kind, data)
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            self._deliver(event)
        else:
            loop.call_soon_threadsafe(self._deliver, event)

    def _deliver(self, event: Event | None) -> None:
        if event is not None:
            self._history.append(event)
        for queue in list(self._subscribers):
            if queue.full():
                queue.get_nowait()
            queue.put_nowait(event)

    async def subscribe(self, *, after: int | None = None) -> AsyncIterator[Event]:
        """Events from now on, until the bus closes; with ``after``, first the kept events
        with a larger id (what a reconnecting client missed)."""
        queue: asyncio.Queue[Event | None] = asyncio.Queue(self.backlog)
        self._subscribers.add(queue)
        try:
            if after is not None:
                for event in [e for e in self._history if e.id > after]:
                    yield event
            while not self.closed:
                event = await queue.get()
                if event is None:
                    return
                yield event
        finally:
            self._subscribers.discard(queue)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)

    def close(self) -> None:
        """End every subscription (at shutdown, so open streams finish)."""
        self.closed = True
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                running = asyncio.get_running_loop()
            except RuntimeError:
                running = None
            if running is loop:
                self._deliver(None)
            else:
                loop.call_soon_threadsafe(self._deliver, None)
