"""``/api/v1/camera``: the camera's state, and pulling new shots now."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import ApiKey, State
from service.problems import Problem
from service.watcher import CameraUnavailable

router = APIRouter(prefix="/api/v1/camera", tags=["camera"])


@router.get("", summary="The camera: serial, battery, state")
async def get_camera(state: State) -> dict:
    if state.watcher is None:
        return {"configured": False, "state": "none", "serial": None, "battery": None}
    return state.watcher.status()


@router.post("/pull", dependencies=[ApiKey], summary="Pull new shots from the camera now")
async def pull(state: State) -> dict:
    if state.watcher is None:
        raise Problem(409, "No camera", "no camera is configured; start the service with --camera "
                      "usb|wifi:HOST|simulated:DIR", kind="no-camera")
    try:
        queued = await state.watcher.pull_now()
    except CameraUnavailable as exc:
        raise Problem(503, "Camera unavailable", f"{exc}; check the cable or network and try again",
                      kind="camera-unavailable", headers={"Retry-After": "5"}) from exc
    return {"queued": queued, "camera": state.watcher.status()}
