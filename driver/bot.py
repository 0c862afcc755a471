"""Bulk-only transport (BOT) to the Lytro F01 over pyusb.

The only module that touches endpoints and translates pyusb errors into
:mod:`driver.errors`. It sends one command at a time (CBW, data phase, CSW), checks
every field of the status wrapper, clears a stalled pipe, and performs reset recovery
(class reset, then clear halt on both pipes) after a phase error, a bad status wrapper
or a timeout. Retrying is left to :class:`driver.camera.Camera`.
"""

from __future__ import annotations

import array
import errno
import logging
from dataclasses import dataclass

import usb.core
import usb.util

from driver import protocol as p
from driver.errors import (CameraBusy, CameraError, CameraGone, CameraPermissionError, CameraTimeout, CommandFailed,
                           ProtocolError)

log = logging.getLogger(__name__)

# libusb-1.0 error codes, for backends that do not set errno.
_LIBUSB_ERROR_IO = -1
_LIBUSB_ERROR_ACCESS = -3
_LIBUSB_ERROR_NO_DEVICE = -4
_LIBUSB_ERROR_BUSY = -6
_LIBUSB_ERROR_PIPE = -9


@dataclass(frozen=True)
class TransportSettings:
    """How the transport talks to the device.

    Attributes
    ----------
    timeout_ms : int
        Timeout of each bulk transfer.
    cdb_length : {16, 12}
        16 as pyly sends, 12 as lyli sends.
    """

    timeout_ms: int = 5000
    cdb_length: int = 16

    def __post_init__(self) -> None:
        if self.timeout_ms <= 0:
            raise ValueError(f"timeout_ms must be positive, got {self.timeout_ms}")
        if self.cdb_length not in (12, 16):
            raise ValueError(f"cdb_length must be 12 or 16, got {self.cdb_length}")


def _is_stall(exc: usb.core.USBError) -> bool:
    return exc.errno == errno.EPIPE or exc.backend_error_code == _LIBUSB_ERROR_PIPE


def _is_gone(exc: usb.core.USBError) -> bool:
    return exc.errno == errno.ENODEV or exc.backend_error_code == _LIBUSB_ERROR_NO_DEVICE


def translate_usb_error(exc: usb.core.USBError, doing: str) -> CameraError:
    """Map a pyusb error to the driver's exception for it."""
    if isinstance(exc, usb.core.USBTimeoutError):
        return CameraTimeout(f"the camera did not answer while {doing}; check the cable, "
                             f"or raise timeout_ms ({exc})")
    if _is_gone(exc):
        return CameraGone(f"the camera disappeared while {doing}; reconnect it and try again ({exc})")
    if exc.errno == errno.EACCES or exc.backend_error_code == _LIBUSB_ERROR_ACCESS:
        return CameraPermissionError(f"no permission to use the camera while {doing}; install "
                                     f"deploy/udev/51-lytro.rules and replug it ({exc})")
    if exc.errno == errno.EBUSY or exc.backend_error_code == _LIBUSB_ERROR_BUSY:
        return CameraBusy(f"the camera is in use by another program while {doing}; close it "
                          f"(lyli, Lytro Desktop, another plenodust) and try again ({exc})")
    return ProtocolError(f"USB error while {doing}: {exc}")


class BulkOnlyTransport:
    """One Lytro F01 over pyusb, speaking bulk-only transport on interface 0.

    Parameters
    ----------
    device : usb.core.Device
        As returned by ``usb.core.find``; any pyusb backend works.
    settings : TransportSettings
        Timeout and CDB length.
    """

    def __init__(self, device: usb.core.Device, settings: TransportSettings | None = None) -> None:
        self.device = device
        self.settings = settings or TransportSettings()
        self._tag = 0
        self._detached_kernel_driver = False
        self._needs_recovery = False
        self._buffers: dict[int, array.array] = {}
        self._open = False

    # -- lifetime ------------------------------------------------------------------

    def open(self) -> None:
        """Detach a kernel driver if one holds interface 0, configure, claim the interface."""
        try:
            try:
                active = self.device.is_kernel_driver_active(p.INTERFACE)
            except NotImplementedError:  # backends without the notion (e.g. on Windows)
                active = False
            if active:
                log.info("detaching the kernel driver from interface %d", p.INTERFACE)
                self.device.detach_kernel_driver(p.INTERFACE)
                self._detached_kernel_driver = True
            try:
                current = self.device.get_active_configuration()
            except usb.core.USBError:
                current = None
            if current is None:
                self.device.set_configuration()
            usb.util.claim_interface(self.device, p.INTERFACE)
        except usb.core.USBError as exc:
            self._open = True
            self.close()  # give back the kernel driver taken above
            raise translate_usb_error(exc, "opening the camera") from exc
        self._open = True

    def close(self) -> None:
        """Release the interface and give the kernel driver back if this transport took it."""
        if not self._open:
            return
        self._open = False
        try:
            usb.util.release_interface(self.device, p.INTERFACE)
            if self._detached_kernel_driver:
                log.info("re-attaching the kernel driver to interface %d", p.INTERFACE)
                self.device.attach_kernel_driver(p.INTERFACE)
                self._detached_kernel_driver = False
        except usb.core.USBError as exc:
            # The camera may already be gone; there is nothing left to give back then.
            log.debug("while closing: %s", exc)
        finally:
            usb.util.dispose_resources(self.device)

    # -- commands ------------------------------------------------------------------

    @property
    def cdb_length(self) -> int:
        return self.settings.cdb_length

    def execute(self, cdb: bytes, *, data_out: bytes | None = None, data_in_length: int = 0) -> memoryview:
        """Run one command: CBW, optional data phase, CSW.

        Parameters
        ----------
        cdb : bytes
            The command block (12 or 16 bytes).
        data_out : bytes, optional
            Payload sent host to device.
        data_in_length : int
            Bytes requested device to host (0 for none). The device may send fewer.

        Returns
        -------
        memoryview
            The bytes received (empty without an IN phase). It views a buffer that the next
            command reuses: copy what you keep.

        Raises
        ------
        CommandFailed
            The device reported status 1 (the transport is fine; the caller may retry).
        CameraTimeout, CameraGone, ProtocolError
            After which the next command first performs reset recovery.
        """
        if data_out is not None and data_in_length:
            raise ValueError("a bulk-only command has at most one data direction")
        if self._needs_recovery:
            self.reset_recovery()
        self._tag = (self._tag + 1) & 0xFFFFFFFF
        tag = self._tag
        expected = len(data_out) if data_out is not None else data_in_length
        cbw = p.encode_cbw(cdb, tag=tag, data_length=expected, direction_in=data_in_length > 0)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("CBW tag %d cdb %s out %s in %d", tag, cdb[:7].hex(),
                      None if data_out is None else len(data_out), data_in_length)
        received = memoryview(b"")
        try:
            self._write(cbw, "sending a command")
            if data_out is not None and expected:
                self._write(data_out, "sending command data", clear_stall=True)
            elif data_in_length:
                buffer = self._buffer(data_in_length)
                count = self._read_into(buffer, "receiving data")
                received = memoryview(buffer)[:count]
            csw = self._read_csw()
        except CameraError:
            self._needs_recovery = True
            raise
        self._check_csw(csw, tag=tag, expected=expected, received=len(received) if data_in_length else None)
        return received

    def recover(self) -> None:
        """Reset recovery; what :class:`driver.camera.Camera` calls after an error."""
        self.reset_recovery()

    def reset_recovery(self) -> None:
        """Bulk-only mass storage reset, then clear halt on both pipes (BOT 1.0, 5.3.4)."""
        log.info("reset recovery")
        try:
            self.device.ctrl_transfer(p.BOT_RESET_REQUEST_TYPE, p.BOT_RESET_REQUEST, 0, p.INTERFACE, None,
                                      timeout=self.settings.timeout_ms)
            self.device.clear_halt(p.EP_IN)
            self.device.clear_halt(p.EP_OUT)
        except usb.core.USBError as exc:
            self._needs_recovery = True
            raise translate_usb_error(exc, "resetting the transport") from exc
        self._needs_recovery = False

    # -- internals -----------------------------------------------------------------

    def _buffer(self, length: int) -> array.array:
        # pyusb reads into an array.array in place; keep one per size to avoid re-allocating.
        buffer = self._buffers.get(length)
        if buffer is None:
            if len(self._buffers) > 8:
                self._buffers.clear()
            buffer = self._buffers[length] = usb.util.create_buffer(length)
        return buffer

    def _write(self, data: bytes, doing: str, *, clear_stall: bool = False) -> None:
        try:
            written = self.device.write(p.EP_OUT, data, self.settings.timeout_ms)
        except usb.core.USBError as exc:
            if clear_stall and _is_stall(exc):
                # The device refused the data; the status wrapper says why.
                self._clear_halt(p.EP_OUT, doing)
                return
            raise translate_usb_error(exc, doing) from exc
        if written != len(data):
            raise ProtocolError(f"wrote {written} of {len(data)} bytes while {doing}")

    def _read_into(self, buffer: array.array, doing: str) -> int:
        try:
            return self.device.read(p.EP_IN, buffer, self.settings.timeout_ms)
        except usb.core.USBError as exc:
            if _is_stall(exc):
                # A stalled data phase ends it; clear the halt and read the status wrapper.
                log.info("data phase stalled; clearing halt on %#04x", p.EP_IN)
                self._clear_halt(p.EP_IN, doing)
                return 0
            raise translate_usb_error(exc, doing) from exc

    def _read_csw(self) -> bytes:
        buffer = self._buffer(p.CSW_LENGTH)
        for attempt in range(2):
            try:
                count = self.device.read(p.EP_IN, buffer, self.settings.timeout_ms)
                return bytes(buffer[:count])
            except usb.core.USBError as exc:
                if _is_stall(exc) and attempt == 0:
                    # BOT 1.0 figure 2: on a stall reading the CSW, clear it and read once more.
                    self._clear_halt(p.EP_IN, "reading the status")
                    continue
                raise translate_usb_error(exc, "reading the command status") from exc
        raise AssertionError("unreachable")

    def _clear_halt(self, endpoint: int, doing: str) -> None:
        try:
            self.device.clear_halt(endpoint)
        except usb.core.USBError as exc:
            raise translate_usb_error(exc, f"clearing a stall while {doing}") from exc

    def _check_csw(self, raw: bytes, *, tag: int, expected: int, received: int | None) -> None:
        try:
            csw = p.decode_csw(raw)
        except ProtocolError as exc:
            self._needs_recovery = True
            raise ProtocolError(f"{exc}; the transport will be reset") from None
        if csw.tag != tag:
            self._needs_recovery = True
            raise ProtocolError(f"status wrapper tag {csw.tag} does not match command tag {tag}; "
                                "the transport will be reset")
        if csw.status == p.CSW_PHASE_ERROR:
            self._needs_recovery = True
            raise ProtocolError("the camera reported a phase error; the transport will be reset")
        if csw.status not in (p.CSW_PASSED, p.CSW_FAILED):
            self._needs_recovery = True
            raise ProtocolError(f"status wrapper has status {csw.status}, which BOT does not define")
        if csw.residue > expected:
            self._needs_recovery = True
            raise ProtocolError(f"status wrapper residue {csw.residue} exceeds the {expected} bytes requested")
        if csw.status == p.CSW_FAILED:
            raise CommandFailed(f"the camera reported that the command failed (residue {csw.residue})")
        if received is not None and received != expected - csw.residue:
            self._needs_recovery = True
            raise ProtocolError(f"received {received} bytes but the camera reports "
                                f"{expected - csw.residue} sent")


def find_device(backend: object | None = None) -> usb.core.Device | None:
    """The first Lytro F01 on the bus, or None; ``backend`` is any pyusb backend object.

    Raises
    ------
    CameraNotFound
        If pyusb finds no USB library to use (libusb-1.0 is missing).
    """
    from driver.errors import CameraNotFound

    try:
        return usb.core.find(idVendor=p.VENDOR_ID, idProduct=p.PRODUCT_ID, backend=backend)
    except usb.core.NoBackendError as exc:
        raise CameraNotFound("pyusb found no USB library; install libusb-1.0 from the OS packages "
                             "(e.g. `apt install libusb-1.0-0`)") from exc
    except usb.core.USBError as exc:
        raise translate_usb_error(exc, "looking for the camera") from exc
