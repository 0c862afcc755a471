"""A request-body size limit, enforced before and while the body is read."""

from __future__ import annotations

import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.problems import PROBLEM_JSON, Problem


def _too_large(limit: int) -> Problem:
    return Problem(413, "Body too large", f"the request body is over the limit of {limit} bytes "
                   "(PLENODUST_MAX_BODY_BYTES, or PLENODUST_MAX_CALIBRATION_BYTES for white images); "
                   "one F01 .lfp is about 16 MB", kind="body-too-large")


class BodySizeLimit:
    """Answer 413 when ``Content-Length`` is over ``limit``; stop a streamed body that grows past it."""

    def __init__(self, app: ASGIApp, *, limit: int, by_path: dict[str, int] | None = None) -> None:
        self.app = app
        self.default_limit = limit
        # Routes that take bigger bodies (a camera's white images are about 1 GB).
        self.by_path = by_path or {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.by_path.get(scope.get("path", "").rstrip("/"), self.default_limit)
        declared = dict(scope.get("headers", [])).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            problem = _too_large(limit)
            body = json.dumps({"type": "https://plenodust.invalid/problems/body-too-large",
                               "title": problem.title, "status": 413, "detail": problem.detail,
                               "instance": scope.get("path")}).encode()
            await send({"type": "http.response.start", "status": 413,
                        "headers": [(b"content-type", PROBLEM_JSON.encode()),
                                    (b"content-length", str(len(body)).encode()),
                                    (b"connection", b"close")]})
            await send({"type": "http.response.body", "body": body})
            return
        seen = 0

        async def limited_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    # Raised inside the route that reads the body, so the problem handler answers.
                    raise _too_large(limit)
            return message

        await self.app(scope, limited_receive, send)


# Longest URL (path and query) served; a longer one is answered 414. The request head as a
# whole (request line and headers) may take HEAD_LIMIT_BYTES before the connection answers.
MAX_URL_BYTES = 8 * 1024
HEAD_LIMIT_BYTES = 64 * 1024


def _problem_bytes(status: int, title: str, detail: str, kind: str) -> bytes:
    return json.dumps({"type": f"https://plenodust.invalid/problems/{kind}", "title": title, "status": status,
                       "detail": detail}).encode()


def _url_too_long(length: int) -> tuple[int, str, str, str]:
    return (414, "URI too long", f"the URL is {length} bytes long, over the limit of {MAX_URL_BYTES}; send large "
            "inputs in the request body (POST) instead of the query", "uri-too-long")


class UrlLengthLimit:
    """Answer 414 to a URL over :data:`MAX_URL_BYTES` that still fitted in the request head."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            length = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"")
            if length > MAX_URL_BYTES:
                status, title, detail, kind = _url_too_long(length)
                body = _problem_bytes(status, title, detail, kind)
                await send({"type": "http.response.start", "status": status,
                            "headers": [(b"content-type", PROBLEM_JSON.encode()),
                                        (b"content-length", str(len(body)).encode())]})
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)


def http_protocol_class() -> type:
    """uvicorn's h11 protocol, answering an over-long request head with a problem document.

    uvicorn answers a request head that outgrows h11's buffer with a bare 400 and closes the
    socket while the client is still sending, which the client sees as a reset connection.
    This one answers 414 (URL too long) or 431 (headers too large) and reads on (discarding)
    until the client has sent its request, so the client gets the answer.
    """
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class HeadLimitedH11Protocol(H11Protocol):
        _discarding = False
        _discarded = 0
        _close_timer: object = None

        def data_received(self, data: bytes) -> None:
            if self._discarding:
                self._discard(data)
                return
            if self.conn.their_state is h11.IDLE:
                pending = bytes(self.conn.trailing_data[0]) + data
                if len(pending) > HEAD_LIMIT_BYTES and b"\r\n\r\n" not in pending:
                    self._refuse(pending)
                    return
            super().data_received(data)

        def _refuse(self, pending: bytes) -> None:
            line_end = pending.find(b"\r\n")
            if line_end < 0:  # the request line itself is too long: the URL
                parts = pending.split(b" ", 2)
                status, title, detail, kind = _url_too_long(len(parts[1]) if len(parts) > 1 else len(pending))
            else:
                status, title, detail, kind = (431, "Request header fields too large",
                                               f"the request's headers are over {HEAD_LIMIT_BYTES} bytes",
                                               "headers-too-large")
            self.logger.warning("refused a request head over %d bytes with %d", HEAD_LIMIT_BYTES, status)
            body = _problem_bytes(status, title, detail, kind)
            self.transport.write(
                f"HTTP/1.1 {status} {title}\r\ncontent-type: {PROBLEM_JSON}\r\ncontent-length: {len(body)}\r\n"
                "connection: close\r\n\r\n".encode() + body)
            self._discarding = True
            if self.timeout_keep_alive_task is not None:
                self.timeout_keep_alive_task.cancel()
                self.timeout_keep_alive_task = None
            self._discard(b"")

        def _discard(self, data: bytes) -> None:
            # Close once the client has been quiet a moment (it has sent its request), or after
            # 64 MB, whichever comes first.
            self._discarded += len(data)
            if self._close_timer is not None:
                self._close_timer.cancel()
            if self._discarded > 64 * 1024 * 1024:
                self.transport.close()
                return
            self._close_timer = self.loop.call_later(0.5, self.transport.close)

        def connection_lost(self, exc: Exception | None) -> None:
            if self._close_timer is not None:
                self._close_timer.cancel()
            super().connection_lost(exc)

    return HeadLimitedH11Protocol
