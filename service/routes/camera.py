"""``/api/v1/camera``: the camera's state, pulling new shots now, and taking a shot."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.deps import ApiKey, State
from service.models import PROBLEM_RESPONSE, CameraStatus, PullResult, QueuedShot
from service.problems import Problem
from service.watcher import CameraUnavailable, ShotNotSeen, ShotsNotSupported

router = APIRouter(prefix="/api/v1/camera", tags=["camera"])


def _watcher(state: State):
    if state.watcher is None:
        raise Problem(409, "No camera", "no camera is configured; start the service with --camera "
                      "usb|wifi:HOST|simulated:DIR", kind="no-camera")
    return state.watcher


def _unavailable(exc: CameraUnavailable) -> Problem:
    return Problem(503, "Camera unavailable", f"{exc}; check the cable or network and try again",
                   kind="camera-unavailable", headers={"Retry-After": "5"})


@router.get("", summary="The camera: serial, battery, state", response_model=CameraStatus)
async def get_camera(state: State) -> dict:
    if state.watcher is None:
        return {"configured": False, "state": "none", "serial": None, "battery": None}
    return state.watcher.status()


@router.post("/pull", dependencies=[ApiKey], summary="Pull new shots from the camera now", response_model=PullResult,
             responses={409: PROBLEM_RESPONSE, 503: PROBLEM_RESPONSE, 507: PROBLEM_RESPONSE})
async def pull(state: State) -> dict:
    watcher = _watcher(state)
    try:
        queued = await watcher.pull_now()
    except CameraUnavailable as exc:
        raise _unavailable(exc) from exc
    return {"queued": queued, "camera": watcher.status()}


@router.post("/shots", status_code=202, dependencies=[ApiKey], response_model=QueuedShot,
             summary="Take a shot, pull it and queue it: one call, then wait for its job",
             description="The camera takes a picture (over Wi-Fi, or a simulated camera with a shutter); the "
                         "picture is pulled, stored under the current run and queued. The answer names the "
                         "exposure and the job (also as Location); wait for the job on GET /api/v1/jobs/{id} or "
                         "the event stream, then read GET /api/v1/exposures/{id}/particles.",
             responses={409: PROBLEM_RESPONSE,
                        501: {**PROBLEM_RESPONSE, "description": "this camera cannot be told to take a picture "
                                                                 "(USB: the command is not known to work)"},
                        503: PROBLEM_RESPONSE, 504: PROBLEM_RESPONSE, 507: PROBLEM_RESPONSE})
async def take_shot(state: State) -> JSONResponse:
    watcher = _watcher(state)
    try:
        shot = await watcher.shoot_now()
    except ShotsNotSupported as exc:
        raise Problem(501, "Cannot take shots", str(exc), kind="shots-not-supported") from exc
    except ShotNotSeen as exc:
        raise Problem(504, "No new picture", f"{exc}; check the camera (battery, card) and try again",
                      kind="no-new-picture") from exc
    except CameraUnavailable as exc:
        raise _unavailable(exc) from exc
    if shot["created"]:
        state.runner.wake()
    return JSONResponse(shot, status_code=202, headers={"Location": f"/api/v1/jobs/{shot['job_id']}"})
