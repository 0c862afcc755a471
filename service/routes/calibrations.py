"""``/api/v1/calibrations``: white images per camera, uploaded where no camera is attached."""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse
from starlette.datastructures import UploadFile

from analysis.errors import AnalysisError
from analysis.whites import load_white_images
from service.deps import ApiKey, State
from service.problems import Problem

router = APIRouter(prefix="/api/v1/calibrations", tags=["calibrations"])

_UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "properties": {"files": {"type": "array", "items": {"type": "string", "format": "binary"},
                                               "description": "MOD_nnnn.RAW + MOD_nnnn.TXT pairs, or data.C.N "
                                                              "bundles"}}}}}}}


def _check_whites(files: dict[str, bytes]) -> list:
    with tempfile.TemporaryDirectory(prefix="plenodust-whites-") as tmp:
        for name, data in files.items():
            (Path(tmp) / name).write_bytes(data)
        bundles = [n for n in files if n.startswith("data.C.")]
        source = Path(tmp) if not bundles or "data.C.0" in files else Path(tmp) / bundles[0]
        return load_white_images(source)


@router.get("", summary="Cameras with white images")
async def list_calibrations(state: State) -> dict:
    return {"items": state.store.calibration_serials()}


@router.post("", status_code=201, dependencies=[ApiKey], openapi_extra=_UPLOAD_BODY,
             summary="Upload a camera's white images (MOD_nnnn.RAW/.TXT or data.C.N)")
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
    form = await request.form(max_files=200, max_fields=10)
    files: dict[str, bytes] = {}
    try:
        for _, value in form.multi_items():
            if isinstance(value, UploadFile) and value.filename:
                name = Path(value.filename.replace("\\", "/")).name
                files[name] = await value.read()
    finally:
        await form.close()
    if not files:
        raise Problem(400, "No files", "the upload holds no files; attach MOD_nnnn.RAW and .TXT files",
                      kind="no-files")
    try:
        whites = await asyncio.to_thread(_check_whites, files)
    except (AnalysisError, OSError) as exc:
        raise Problem(422, "Not white images", str(exc), kind="not-white-images") from exc
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
    await asyncio.to_thread(state.store.add_calibration, camera_serial, files, source="upload")
    state.bus.publish("calibration", {"serial": camera_serial, "images": len(whites)})
    return JSONResponse({"serial": camera_serial, "white_images": len(whites)}, status_code=201,
                        headers={"Location": "/api/v1/calibrations"})
