"""``/api/v1/exposures``: upload an exposure, read its particle table, curves and slices."""

from __future__ import annotations

import asyncio
from typing import Annotated

import cv2
from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response
from starlette.datastructures import UploadFile

from service.deps import ApiKey, State
from service.ingest import NotAnExposure, ingest, parse_exposure
from service.models import PROBLEM_RESPONSE, Curves, ExposureInfo, ParticleTable, UploadAccepted
from service.problems import Problem
from service.queue import QueueFull
from service.settings import RUN_NAME_PATTERN
from service.tables import TableFormat, choose_format, table_response

router = APIRouter(prefix="/api/v1/exposures", tags=["exposures"])

LFP_MAGIC = b"\x89LFP\r\n\x1a\n"

_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"},
                                         "example": "(the bytes of an .lfp picture)"},
            "multipart/form-data": {"schema": {
                "type": "object", "required": ["raw"],
                "properties": {"raw": {"type": "string", "format": "binary",
                                       "description": "the camera's .RAW (or an .lfp)"},
                               "metadata": {"type": "string", "format": "binary",
                                            "description": "the .TXT beside the .RAW"}}}},
        },
    },
}


async def _field_bytes(value: object) -> bytes | None:
    if value is None:
        return None
    if isinstance(value, UploadFile):
        return await value.read()
    return str(value).encode()


async def _read_upload(request: Request) -> dict[str, bytes]:
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media in ("application/octet-stream", "application/x-lytro-lfp"):
        body = await request.body()
        if not body:
            raise Problem(400, "Empty upload", "the request body is empty; send the bytes of an .lfp",
                          kind="empty-upload")
        return {".lfp": body}
    if media == "multipart/form-data":
        form = await request.form(max_files=4, max_fields=8)
        try:
            raw = await _field_bytes(form.get("raw"))
            txt = await _field_bytes(form.get("metadata"))
        finally:
            await form.close()
        if not raw:
            raise Problem(400, "Missing field", "a multipart upload needs a field 'raw' (the .RAW, or an "
                          ".lfp) and, for a .RAW, a field 'metadata' (its .TXT)", kind="missing-field")
        if raw.startswith(LFP_MAGIC) and not txt:
            return {".lfp": raw}
        if not txt:
            raise Problem(400, "Missing field", "field 'metadata' (the .TXT beside the .RAW) is missing",
                          kind="missing-field")
        return {".RAW": raw, ".TXT": txt}
    raise Problem(415, "Unsupported media type",
                  f"cannot read an upload of type {media or '(none)'!r}: send an .lfp as "
                  "application/octet-stream, or a .RAW + .TXT pair as multipart/form-data with "
                  "fields 'raw' and 'metadata'", kind="unsupported-media-type")


@router.post("", status_code=202, dependencies=[ApiKey], openapi_extra=_UPLOAD_BODY,
             summary="Upload one raw exposure and queue it", response_model=UploadAccepted,
             responses={200: {"model": UploadAccepted,
                              "description": "this exposure was uploaded before; its job (queued again "
                                             "with 202 if it had failed)"},
                        400: PROBLEM_RESPONSE, 413: PROBLEM_RESPONSE, 415: PROBLEM_RESPONSE, 422: PROBLEM_RESPONSE,
                        503: {**PROBLEM_RESPONSE, "description": "queue full; retry after Retry-After seconds"},
                        507: {**PROBLEM_RESPONSE, "description": "the data disk is full: the problem names the "
                                                                 "data folder and the space needed"}})
async def upload_exposure(
        request: Request, state: State,
        run: Annotated[str | None, Query(pattern=RUN_NAME_PATTERN,
                                         description="run name; default: the current run")] = None,
        serial: Annotated[str | None, Query(max_length=64, pattern=r"^[A-Za-z0-9_-]+$",
                                            description="camera serial, if the metadata lacks it")] = None,
) -> JSONResponse:
    run_name = run or state.current_run
    try:
        # Refuse before reading 16 MB when the answer is known already.
        await asyncio.to_thread(state.queue.check_room)
    except QueueFull:
        state.metrics.inc("plenodust_uploads_total", result="rejected")
        raise
    declared = request.headers.get("content-length", "")
    await asyncio.to_thread(state.disk.require, int(declared) if declared.isdigit() else 0, what="this upload")
    # Bodies are read and decoded a few at a time: many uploads at once wait here (in TCP
    # back-pressure) instead of each holding ~100 MB of the server's memory.
    async with state.upload_slots:
        files = await _read_upload(request)
        try:
            exposure = await asyncio.to_thread(parse_exposure, files)
        except NotAnExposure as exc:
            state.metrics.inc("plenodust_uploads_total", result="invalid")
            raise Problem(422, "Not an exposure", f"{exc}", kind="not-an-exposure") from exc
        try:
            accepted = await asyncio.to_thread(ingest, state.store, state.queue, files, run=run_name,
                                               source="upload", serial=serial, exposure=exposure,
                                               guard=state.disk)
        except QueueFull:
            state.metrics.inc("plenodust_uploads_total", result="rejected")
            raise
        del exposure
    queued = accepted.created or accepted.retried
    state.metrics.inc("plenodust_uploads_total", result="accepted" if queued else "duplicate")
    if queued:
        state.runner.wake()
        state.bus.publish("job", {**accepted.job.public(), "run": accepted.exposure.run,
                                  "frame": accepted.exposure.frame})
    location = f"/api/v1/jobs/{accepted.job.id}"
    return JSONResponse({"exposure_id": accepted.exposure.id, "job_id": accepted.job.id,
                         "run": accepted.exposure.run, "frame": accepted.exposure.frame,
                         "created": accepted.created, "retried": accepted.retried},
                        status_code=202 if queued else 200, headers={"Location": location})


def _exposure_or_404(state: State, exposure_id: str):
    record = state.store.exposure(exposure_id)
    if record is None:
        raise Problem(404, "Not found", f"no exposure {exposure_id!r}; upload it with POST /api/v1/exposures",
                      kind="exposure-not-found")
    return record


def _result_or_409(state: State, exposure_id: str):
    record = _exposure_or_404(state, exposure_id)
    if not state.store.has_result(exposure_id):
        job = state.queue.for_exposure(exposure_id)
        where = f"its job {job.id} is {job.state}" if job else "it has no job"
        raise Problem(409, "No result yet", f"exposure {exposure_id} has no result: {where}; "
                      f"watch GET /api/v1/jobs/{job.id if job else ''} or the event stream",
                      kind="no-result", job_id=job.id if job else None)
    return record


@router.get("/{exposure_id}", summary="An exposure and its latest job", response_model=ExposureInfo,
            responses={404: PROBLEM_RESPONSE})
async def get_exposure(exposure_id: str, state: State) -> dict:
    record = _exposure_or_404(state, exposure_id)
    job = state.queue.for_exposure(exposure_id)
    slice_alpha, binning, provenance = [], 1, {}
    if state.store.has_result(exposure_id):
        alphas, binning = await asyncio.to_thread(state.store.slice_info, exposure_id)
        slice_alpha = alphas.tolist()
        provenance = await asyncio.to_thread(state.store.read_provenance, exposure_id)
    return {"id": record.id, "run": record.run, "frame": record.frame, "kind": record.kind,
            "source": record.source, "serial": record.serial, "created_at": record.created_at,
            "job": job.public() if job else None, "raw_kept": record.raw_kept, "slices": len(slice_alpha),
            "slice_alpha": slice_alpha, "slice_binning": binning,
            # What the pipeline wants a user to know (nothing found, saturation, ...) and its timings.
            "warnings": provenance.get("warnings", []), "timings": provenance.get("timings", {}),
            "coordinates": provenance.get("coordinates")}


@router.get("/{exposure_id}/particles", summary="The particle table of one exposure",
            response_model=ParticleTable,
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}},
                                         "application/x-hdf5": {"schema": {"type": "string", "format": "binary"}}}},
                       404: PROBLEM_RESPONSE, 406: PROBLEM_RESPONSE,
                       409: {**PROBLEM_RESPONSE, "description": "no result yet: the problem names the job"}})
async def get_particles(exposure_id: str, request: Request, state: State,
                        format: TableFormat | None = None) -> Response:
    fmt = choose_format(request, format)
    record = _result_or_409(state, exposure_id)
    columns = await asyncio.to_thread(state.store.read_columns, exposure_id)
    return table_response(columns, fmt, meta={"exposure_id": record.id, "run": record.run,
                                              "frame": record.frame},
                          filename=f"{record.run}-{record.frame:05d}")


@router.get("/{exposure_id}/curves", summary="Brightness curves B(alpha) of the particles", response_model=Curves,
            responses={404: PROBLEM_RESPONSE, 409: PROBLEM_RESPONSE})
async def get_curves(exposure_id: str, state: State,
                     particle: Annotated[int | None, Query(ge=0)] = None) -> dict:
    _result_or_409(state, exposure_id)
    curves = await asyncio.to_thread(state.store.read_curves, exposure_id)
    if curves is None:
        raise Problem(404, "No curves", "the pipeline kept no brightness curves for this exposure",
                      kind="no-curves")
    alpha, brightness = curves
    if particle is not None:
        if particle >= brightness.shape[0]:
            raise Problem(404, "No such particle", f"particle {particle} not in 0..{brightness.shape[0] - 1}",
                          kind="no-particle")
        brightness = brightness[particle:particle + 1]
    return {"alpha": alpha.tolist(), "brightness": brightness.tolist(),
            "particles": list(range(particle, particle + 1)) if particle is not None
            else list(range(brightness.shape[0]))}


@router.get("/{exposure_id}/slices/{index}", summary="One refocused slice as a PNG",
            response_class=Response,
            responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                             "description": "an 8-bit image; headers X-Alpha (its alpha) and X-Binning (output-image "
                                            "pixels per image pixel)"},
                       404: PROBLEM_RESPONSE, 409: PROBLEM_RESPONSE})
async def get_slice(exposure_id: str, index: int, state: State) -> Response:
    _result_or_409(state, exposure_id)
    found = await asyncio.to_thread(state.store.read_slice, exposure_id, index)
    if found is None:
        raise Problem(404, "No such slice", f"exposure {exposure_id} has no kept slice {index}",
                      kind="no-slice")
    alpha, image, binning = found
    ok, png = cv2.imencode(".png", image)
    # X-Binning: particle x, y (output-image pixels) / binning = position in this image.
    return Response(png.tobytes(), media_type="image/png",
                    headers={"X-Alpha": f"{alpha:.6f}", "X-Binning": str(binning)})
