"""Open a camera: over USB, over Wi-Fi, or simulated from a folder."""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Iterable

from driver import protocol as p
from driver.bot import BulkOnlyTransport, TransportSettings, find_device
from driver.camera import Camera, CameraSettings
from driver.errors import CameraError, CameraNotFound
from driver.simulated import CameraIdentity, Shutter
from driver.simulated_usb import SimulatedBackend
from driver.wifi import WifiTransport

_CAMERA_FIELDS = {f.name for f in dataclasses.fields(CameraSettings)}
_TRANSPORT_FIELDS = {f.name for f in dataclasses.fields(TransportSettings)}


def _split(settings: dict[str, Any], transport_fields: set[str]) -> tuple[CameraSettings, dict[str, Any]]:
    unknown = set(settings) - _CAMERA_FIELDS - transport_fields
    if unknown:
        raise TypeError(f"unknown camera setting(s) {', '.join(sorted(unknown))}; known: "
                        f"{', '.join(sorted(_CAMERA_FIELDS | transport_fields))}")
    camera = CameraSettings(**{k: v for k, v in settings.items() if k in _CAMERA_FIELDS})
    return camera, {k: v for k, v in settings.items() if k in transport_fields}


def open_usb(backend: object | None = None, **settings: Any) -> Camera:
    """Open the first Lytro F01 on USB and wait until it is ready.

    Parameters
    ----------
    backend : pyusb backend, optional
        Passed to ``usb.core.find(idVendor=0x24cf, idProduct=0x00a1, backend=backend)``;
        None lets pyusb pick libusb-1.0. A :class:`driver.simulated_usb.SimulatedBackend`
        stands in for the hardware.
    **settings
        Fields of :class:`driver.camera.CameraSettings` (``chunk_size``, ``retries``, ...)
        and :class:`driver.bot.TransportSettings` (``timeout_ms``, ``cdb_length``).

    Raises
    ------
    CameraNotFound
        No camera is connected (or libusb-1.0 is missing).
    """
    camera_settings, transport_settings = _split(settings, _TRANSPORT_FIELDS)
    device = find_device(backend)
    if device is None:
        raise CameraNotFound("no Lytro F01 (USB 24cf:00a1) found; connect it, switch it on, and check "
                             "`lsusb`; without root, install deploy/udev/51-lytro.rules")
    transport = BulkOnlyTransport(device, TransportSettings(**transport_settings))
    transport.open()
    camera = Camera(transport, camera_settings)
    try:
        camera.wait_ready()
    except CameraError:
        transport.close()
        raise
    return camera


def open_wifi(host: str = "10.100.1.1", port: int = p.WIFI_COMMAND_PORT, *,
              callback_port: int | None = p.WIFI_CALLBACK_PORT, timeout_s: float = 5.0, **settings: Any) -> Camera:
    """Connect to an F01 over Wi-Fi (firmware 1.2 or later).

    New-picture callbacks (port 5677) wake :meth:`Camera.watch` at once; listeners may be
    added to ``camera.transport.listeners``. ``download_subcode`` defaults to 1, as over USB;
    pass 0 for the variant of Kucera's library.
    """
    camera_settings, _ = _split(settings, set())
    transport = WifiTransport(host, port, callback_port=callback_port, timeout_s=timeout_s)
    transport.open()
    camera = Camera(transport, camera_settings)

    def wake(name: str, arg: str) -> None:
        if name == p.NEW_PICTURE_CALLBACK:
            camera.new_picture.set()

    transport.listeners.append(wake)
    camera.can_take_pictures = True
    return camera


def open_simulated(folder: str | os.PathLike, *, faults: Iterable[str | tuple[str, int, int | None]] = (),
                   shutter: Shutter | None = None, serial: str | None = None, **settings: Any) -> Camera:
    """A camera simulated over USB from a folder (see :mod:`driver.simulated`).

    ``open_usb(backend=SimulatedBackend(folder))`` with ``verify_id=True`` by default, since the
    simulated camera's ids are SHA-1s of the ``.RAW``. The backend is
    ``camera.transport.device.backend``; ``faults`` are kinds or ``(kind, after, count)``
    tuples passed to its :meth:`~driver.simulated_usb.SimulatedBackend.inject`. The camera reports
    ``serial``, by default the one its white images carry (:meth:`CameraFolder.serial`). With a
    ``shutter`` it can take pictures (``camera.can_take_pictures``).
    """
    extra = {"identity": CameraIdentity(serial=serial)} if serial else {}
    backend = SimulatedBackend(folder, shutter=shutter, **extra)
    for fault in faults:
        kind, after, count = (fault, 0, 1) if isinstance(fault, str) else fault
        backend.inject(kind, after=after, count=count)
    settings.setdefault("verify_id", True)
    camera = open_usb(backend, **settings)
    camera.can_take_pictures = shutter is not None
    return camera
