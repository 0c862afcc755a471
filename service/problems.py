"""Errors as ``application/problem+json`` (RFC 9457), mapped in one place."""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.disk import NoSpace, is_out_of_space
from service.queue import QueueFull

log = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"
_TYPE_BASE = "https://plenodust.invalid/problems/"


class Problem(Exception):
    """An error a client caused or can act on, answered as a problem document.

    Parameters
    ----------
    status : int
        HTTP status code.
    title : str
        Short, fixed summary of the problem type.
    detail : str
        What happened and what to do about it.
    kind : str
        Slug of the problem type (becomes the ``type`` URI).
    headers : dict, optional
        Extra response headers (``Retry-After``, ``WWW-Authenticate``).
    """

    def __init__(self, status: int, title: str, detail: str, *, kind: str | None = None,
                 headers: dict[str, str] | None = None, **extra: object) -> None:
        super().__init__(detail)
        self.status = status
        self.title = title
        self.detail = detail
        self.kind = kind or title.lower().replace(" ", "-")
        self.headers = headers or {}
        self.extra = extra


def problem_response(status: int, title: str, detail: str, *, kind: str, instance: str | None = None,
                     headers: dict[str, str] | None = None, **extra: object) -> JSONResponse:
    body = {"type": _TYPE_BASE + kind, "title": title, "status": status, "detail": detail}
    if instance:
        body["instance"] = instance
    body.update(extra)
    return JSONResponse(body, status_code=status, headers=headers, media_type=PROBLEM_JSON)


def no_space_response(detail: str, *, instance: str | None, data_dir: str | None,
                      needed_bytes: int | None = None, free_bytes: int | None = None) -> JSONResponse:
    """507 Insufficient Storage, naming the data folder and the space needed."""
    return problem_response(507, "Insufficient storage", detail, kind="insufficient-storage", instance=instance,
                            data_dir=data_dir, needed_bytes=needed_bytes, free_bytes=free_bytes)


def install_problem_handlers(app: FastAPI, *, data_dir: Path | None = None) -> None:
    """Answer every error, expected or not, with a problem document.

    ``data_dir`` is named in the answer to a write that found the data disk full.
    """

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> JSONResponse:
        return problem_response(exc.status, exc.title, exc.detail, kind=exc.kind,
                                instance=request.url.path, headers=exc.headers, **exc.extra)

    @app.exception_handler(QueueFull)
    async def _queue_full(request: Request, exc: QueueFull) -> JSONResponse:
        return problem_response(503, "Queue full", str(exc), kind="queue-full", instance=request.url.path,
                                headers={"Retry-After": str(exc.retry_after_s)})

    @app.exception_handler(NoSpace)
    async def _no_space(request: Request, exc: NoSpace) -> JSONResponse:
        return no_space_response(str(exc), instance=request.url.path, data_dir=str(exc.data_dir),
                                 needed_bytes=exc.needed_bytes, free_bytes=exc.free_bytes)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        titles = {404: "Not found", 405: "Method not allowed", 401: "Unauthorized"}
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"nothing at {request.url.path}; see /docs for the API"
        return problem_response(exc.status_code, titles.get(exc.status_code, "HTTP error"), detail,
                                kind=f"http-{exc.status_code}", instance=request.url.path,
                                headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", "")} for e in exc.errors()]
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors)
        return problem_response(422, "Invalid request", detail, kind="invalid-request",
                                instance=request.url.path, errors=errors)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        if is_out_of_space(exc):
            # The disk filled up during the write (the margin check passed just before).
            # Content-Length is what this request needed; nothing half-written is kept.
            needed = request.headers.get("content-length")
            log.warning("%s %s: the data disk is full (%s)", request.method, request.url.path, exc)
            return no_space_response(
                f"the data folder {data_dir} ran out of space while storing this request"
                + (f" ({needed} bytes)" if needed else "") + "; free space on that disk and send it again",
                instance=request.url.path, data_dir=str(data_dir) if data_dir else None,
                needed_bytes=int(needed) if needed and needed.isdigit() else None)
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(500, "Internal error", f"{type(exc).__name__}: the server failed; "
                                "see its log", kind="internal-error", instance=request.url.path)
