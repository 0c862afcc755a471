"""``/api/v1/calibrations/metric``: target calibrations (X, Y, Z in mm) per camera, zoom and focus."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from analysis.errors import MetricCalibrationError
from service import metric_calibrations
from service.deps import ApiKey, State
from service.models import PROBLEM_RESPONSE, MetricCalibrationInfo, MetricCalibrationList
from service.problems import Problem

router = APIRouter(prefix="/api/v1/calibrations/metric", tags=["calibrations"])

#: A calibration file is tens of kB; refuse anything far bigger before reading it.
MAX_METRIC_BYTES = 8 * 1024 * 1024

_UPLOAD_BODY = {"requestBody": {"required": True, "description": "the JSON file plenodust calibrate-target wrote",
                                "content": {"application/json": {"schema": {"type": "object"}}}}}


@router.get("", summary="Target calibrations, one per camera, zoom and focus", response_model=MetricCalibrationList)
async def list_metric_calibrations(state: State) -> dict:
    return {"items": await asyncio.to_thread(metric_calibrations.listing, state.store.metric_dir)}


@router.post("", status_code=201, dependencies=[ApiKey], openapi_extra=_UPLOAD_BODY,
             summary="Upload a target calibration (plenodust calibrate-target's JSON file)",
             response_model=MetricCalibrationInfo,
             responses={413: PROBLEM_RESPONSE, 415: PROBLEM_RESPONSE, 422: PROBLEM_RESPONSE})
async def upload_metric_calibration(request: Request, state: State) -> JSONResponse:
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media != "application/json":
        raise Problem(415, "Unsupported media type", "send the calibration file as application/json",
                      kind="unsupported-media-type")
    data = await request.body()
    if len(data) > MAX_METRIC_BYTES:
        raise Problem(413, "Too large", f"a target calibration is tens of kB; this upload has {len(data)} bytes",
                      kind="body-too-large")
    try:
        calibration, path = await asyncio.to_thread(metric_calibrations.adopt, state.store.metric_dir, data)
    except MetricCalibrationError as exc:
        raise Problem(422, "Not a target calibration", str(exc), kind="not-a-metric-calibration") from exc
    info = metric_calibrations.describe(calibration, path)
    state.bus.publish("calibration", {"serial": calibration.camera.serial, "metric": info["file"]})
    return JSONResponse(info, status_code=201, headers={"Location": "/api/v1/calibrations/metric"})
