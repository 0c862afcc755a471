"""``/api/v1/calibrations``: white images per camera, uploaded where no camera is attached."""

from __future__ import annotations

import asyncio
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, BinaryIO

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse
from starlette.datastructures import UploadFile

from analysis.errors import AnalysisError
from analysis.formats.whites import load_white_images
from service.deps import ApiKey, State
from service.models import PROBLEM_RESPONSE, CalibrationList, CalibrationUploaded
from service.problems import Problem

router = APIRouter(prefix="/api/v1/calibrations", tags=["calibrations"])

_UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "properties": {"files": {"type": "array", "items": {"type": "string", "format": "binary"},
                                               "description": "MOD_nnnn.RAW + MOD_nnnn.TXT pairs, or data.C.N "
                                                              "bundles"}}}}}}}


def _check_whites(folder: Path) -> list:
    bundles = sorted(folder.glob("data.C.*"))
    source = folder if not bundles or (folder / "data.C.0").is_file() else bundles[0]
    return load_white_images(source)


def _copy(source: BinaryIO, target: Path) -> None:
    with open(target, "wb") as out:
        shutil.copyfileobj(source, out, length=1024 * 1024)


@router.get("", summary="Cameras with white images", response_model=CalibrationList)
async def list_calibrations(state: State) -> dict:
    return {"items": state.store.calibration_serials()}


@router.post("", status_code=201, dependencies=[ApiKey], openapi_extra=_UPLOAD_BODY,
             summary="Upload a camera's white images (MOD_nnnn.RAW/.TXT or data.C.N)",
             response_model=CalibrationUploaded,
             responses={400: PROBLEM_RESPONSE, 413: PROBLEM_RESPONSE, 415: PROBLEM_RESPONSE, 422: PROBLEM_RESPONSE,
                        507: PROBLEM_RESPONSE})
async def upload_calibration(
        request: Request, state: State,
        serial: Annotated[str | None, Query(max_length=64, pattern=r"^[A-Za-z0-9_-]+$",
                                            description="camera serial, if the .TXT files lack it")] = None,
) -> JSONResponse:
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media != "multipart/form-data":
        raise Problem(415, "Unsupported media type", "send the white images as multipart/form-data, one "
                      "file per part, named as on the camera (MOD_0000.RAW, MOD_0000.TXT, ...)",
                      kind="unsupported-media-type")
    declared = request.headers.get("content-length", "")
    await asyncio.to_thread(state.disk.require, int(declared) if declared.isdigit() else 0,
                            what="these white images")
    # Files go straight to a folder on the data disk: a camera's white images are ~1 GB.
    staging = Path(tempfile.mkdtemp(prefix=".upload-", dir=state.store.calibrations_dir))
    try:
        form = await request.form(max_files=400, max_fields=10)
        try:
            count = 0
            for _, value in form.multi_items():
                if isinstance(value, UploadFile) and value.filename:
                    name = Path(value.filename.replace("\\", "/")).name.lstrip(".") or "unnamed"
                    await asyncio.to_thread(_copy, value.file, staging / name)
                    count += 1
        finally:
            await form.close()
        if not count:
            raise Problem(400, "No files", "the upload holds no files; attach MOD_nnnn.RAW and .TXT files",
                          kind="no-files")
        try:
            whites = await asyncio.to_thread(_check_whites, staging)
        except (AnalysisError, OSError) as exc:
            # Name the files as the client sent them, never the server's staging folder.
            detail = str(exc).replace(f"{staging}/", "").replace(str(staging), "the upload")
            raise Problem(422, "Not white images", detail, kind="not-white-images") from exc
        camera_serial = _one_serial(whites, serial)
        await asyncio.to_thread(state.store.adopt_calibration, camera_serial, staging, source="upload")
    finally:
        await asyncio.to_thread(shutil.rmtree, staging, True)
    # Jobs that failed for want of this camera's white images run now, whatever the analysis
    # called the failure (none found, another camera's, a failed fit).
    retried = await asyncio.to_thread(state.queue.retry_waiting, "calibration", serial=camera_serial)
    if retried:
        state.runner.wake()
    for job in retried:
        state.bus.publish("job", job.public())
    state.bus.publish("calibration", {"serial": camera_serial, "images": len(whites)})
    return JSONResponse({"serial": camera_serial, "white_images": len(whites),
                         "jobs_retried": [job.id for job in retried]}, status_code=201,
                        headers={"Location": "/api/v1/calibrations"})


def _one_serial(whites: list, serial: str | None) -> str:
    """The camera the white images belong to, or a problem saying why it is unclear."""
    serials = {w.serial for w in whites if w.serial}
    if len(serials) > 1:
        raise Problem(422, "Several cameras", f"the white images come from cameras {sorted(serials)}; upload "
                      "one camera's at a time", kind="several-cameras")
    camera_serial = serials.pop() if serials else serial
    if camera_serial is None:
        raise Problem(422, "Serial unknown", "the white images do not name their camera; give ?serial=",
                      kind="serial-unknown")
    if serial and serial != camera_serial:
        raise Problem(422, "Serial mismatch", f"the white images are from {camera_serial}, not {serial}",
                      kind="serial-mismatch")
    return camera_serial
