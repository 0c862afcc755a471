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
