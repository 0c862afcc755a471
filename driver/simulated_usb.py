"""A simulated Lytro F01 on USB: a pyusb backend that emulates the device at the byte level.

:class:`SimulatedBackend` implements ``usb.backend.IBackend``: it enumerates one device
(24cf:00a1) with device, configuration, interface and endpoint descriptors, answers
standard and class control requests (string descriptors, SET_CONFIGURATION, CLEAR_FEATURE
ENDPOINT_HALT, bulk-only mass storage reset 0xFF, GET MAX LUN 0xFE), and runs the
bulk-only transport state machine (CBW, data phase, CSW) on endpoints 0x02 / 0x82 in front
of a :class:`driver.simulated.SimulatedCamera`. So ``usb.core.find(..., backend=...)``,
``dev.set_configuration()``, ``usb.util.claim_interface``, ``dev.write/read`` and
``ctrl_transfer`` all go through pyusb's own code.

Faults (see :class:`driver.simulated.FaultPlan`) are injected with :meth:`SimulatedBackend.inject`.
"""

from __future__ import annotations

import errno
import os
import struct
import threading
from collections import deque
from dataclasses import dataclass
from types import SimpleNamespace

import usb.backend
import usb.core
import usb.util

from driver import protocol as p
from driver.errors import ProtocolError
from driver.simulated import CameraFolder, FaultPlan, SimulatedCamera

_IDLE, _DATA_OUT, _DATA_IN, _STATUS = "idle", "data-out", "data-in", "status"
_STRINGS = {1: "Lytro, Inc.", 2: "Lytro Light Field Camera"}  # 3: serial, from the identity
_WIRE_DATA_LIMIT = 4096
_NO_FAULTS: frozenset[str] = frozenset()  # IN transfers longer than this are logged by length only


def _pipe_error() -> usb.core.USBError:
    return usb.core.USBError("Pipe error", -9, errno.EPIPE)


def _no_device() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)


@dataclass(frozen=True)
class Transfer:
    """One bulk transfer as seen on the wire (``data`` empty when only ``length`` is kept)."""

    endpoint: int
    data: bytes
    length: int


class _Device:
    """The opaque device token handed to pyusb."""

    def __repr__(self) -> str:
        return "<simulated Lytro F01>"


class SimulatedBackend(usb.backend.IBackend):
    """A pyusb backend with one simulated Lytro F01 on it.

    Parameters
    ----------
    folder : path or CameraFolder, optional
        The camera's file system (see :mod:`driver.simulated`). Give this or ``camera``.
    camera : SimulatedCamera, optional
        A ready command engine (for a custom identity, shutter or clock).
    kernel_driver_active : bool
        Pretend that ``usb-storage`` holds interface 0 at first, so the driver's
        detach / re-attach path runs.
    **camera_settings
        Passed to :class:`SimulatedCamera` when ``folder`` is given.

    Examples
    --------
    >>> import usb.core, tempfile
    >>> backend = SimulatedBackend(tempfile.mkdtemp())
    >>> hex(usb.core.find(idVendor=0x24cf, idProduct=0x00a1, backend=backend).idVendor)
    '0x24cf'
    """

    def __init__(self, folder: str | os.PathLike | CameraFolder | None = None, *,
                 camera: SimulatedCamera | None = None, kernel_driver_active: bool = True,
                 **camera_settings) -> None:
        super().__init__()
        self.camera = SimulatedCamera.of(folder, camera, **camera_settings)
        self.faults = FaultPlan()
        self.gone = False
        self.kernel_driver_active = {p.INTERFACE: kernel_driver_active}
        self.held_by_another_program = False  # claim_interface then fails with "busy"
        self.configuration = 0
        self.claimed: set[int] = set()
        self.halted = {p.EP_IN: False, p.EP_OUT: False}
        self.wire: deque[Transfer] = deque(maxlen=20000)
        self.control_log: list[tuple[int, int, int, int]] = []
        self.resets = 0
        self._device = _Device()
        self._lock = threading.RLock()
        self._phase = _IDLE
        self._needs_reset = False  # after an invalid CBW, until reset recovery
        self._cbw: p.CommandBlockWrapper | None = None
        self._out = bytearray()
        self._reply: bytes | memoryview = b""
        self._ok = True
        self._residue = 0
        self._hits: frozenset[str] | set[str] = _NO_FAULTS

    # -- test and demo controls ----------------------------------------------------

    def inject(self, kind: str, *, after: int = 0, count: int | None = 1) -> None:
        """Inject a fault into the download command ``after`` downloads from now (see FaultPlan)."""
        with self._lock:
            self.faults.add(kind, after=after, count=count)

    def replug(self) -> None:
        """Bring a camera that went away back, freshly enumerated."""
        with self._lock:
            self.faults.faults = [f for f in self.faults.faults if f.kind != "gone"]
            self.gone = False
            self._bus_reset()
            self.configuration = 0
            self.claimed.clear()
            self.kernel_driver_active[p.INTERFACE] = True
            self.camera.reboot()

    # -- enumeration and descriptors -----------------------------------------------

    def enumerate_devices(self):
        if not self.gone:
            yield self._device

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=usb.util.DESC_TYPE_DEVICE, bcdUSB=0x0200, bDeviceClass=0,
            bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=p.VENDOR_ID,
            idProduct=p.PRODUCT_ID, bcdDevice=0x0100, iManufacturer=1, iProduct=2, iSerialNumber=3,
            bNumConfigurations=1, address=5, bus=1, port_number=1, port_numbers=(1,), speed=3)

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(f"the simulated camera has one configuration, not {config + 1}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=usb.util.DESC_TYPE_CONFIG, wTotalLength=9 + 9 + 7 + 7, bNumInterfaces=1,
            bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=250, extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError("the simulated camera has one interface with one setting")
        # Mass storage, SFF-8070i, bulk-only (pyly's notes on the real camera).
        return SimpleNamespace(
            bLength=9, bDescriptorType=usb.util.DESC_TYPE_INTERFACE, bInterfaceNumber=p.INTERFACE,
            bAlternateSetting=0, bNumEndpoints=2, bInterfaceClass=0x08, bInterfaceSubClass=0x05,
            bInterfaceProtocol=0x50, iInterface=0, extra_descriptors=[])

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0 or ep not in (0, 1):
            raise IndexError("the simulated camera has two endpoints")
        address = (p.EP_OUT, p.EP_IN)[ep]
        return SimpleNamespace(
            bLength=7, bDescriptorType=usb.util.DESC_TYPE_ENDPOINT, bEndpointAddress=address,
            bmAttributes=usb.util.ENDPOINT_TYPE_BULK, wMaxPacketSize=512, bInterval=0, bRefresh=0,
            bSynchAddress=0, extra_descriptors=[])

    # -- device handle -------------------------------------------------------------

    def open_device(self, dev):
        self._check_present()
        return SimpleNamespace(device=dev)

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        self._check_present()
        if config_value not in (0, 1):
            raise _pipe_error()
        with self._lock:
            self.configuration = config_value
            self._bus_reset()

    def get_configuration(self, dev_handle):
        self._check_present()
        return self.configuration

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._check_present()
        if intf != p.INTERFACE or altsetting != 0:
            raise _pipe_error()

    def claim_interface(self, dev_handle, intf):
        self._check_present()
        if self.kernel_driver_active.get(intf) or self.held_by_another_program:
            raise usb.core.USBError("Resource busy", -6, errno.EBUSY)
        self.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        self._check_present()
        self.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle, intf):
        self._check_present()
        return bool(self.kernel_driver_active.get(intf))

    def detach_kernel_driver(self, dev_handle, intf):
        self._check_present()
        self.kernel_driver_active[intf] = False

    def attach_kernel_driver(self, dev_handle, intf):
        self._check_present()
        if intf in self.claimed:
            raise usb.core.USBError("Resource busy (interface still claimed)", -6, errno.EBUSY)
        self.kernel_driver_active[intf] = True

    def reset_device(self, dev_handle):
        self._check_present()
        with self._lock:
            self._bus_reset()

    def clear_halt(self, dev_handle, ep):
        self._check_present()
        with self._lock:
            self.control_log.append((0x02, 0x01, 0, ep))
            self._clear_halt(ep)

    # -- control transfers ---------------------------------------------------------

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        self._check_present()
        with self._lock:
            self.control_log.append((bmRequestType, bRequest, wValue, wIndex))
            if bmRequestType == 0x80 and bRequest == 0x06:  # GET_DESCRIPTOR
                return self._fill(data, self._descriptor(wValue >> 8, wValue & 0xFF))
            if bmRequestType == 0x00 and bRequest == 0x09:  # SET_CONFIGURATION
                self.set_configuration(dev_handle, wValue)
                return 0
            if bmRequestType == 0x02 and bRequest == 0x01 and wValue == 0:  # CLEAR_FEATURE(ENDPOINT_HALT)
                self._clear_halt(wIndex)
                return 0
            if (bmRequestType, bRequest) == (p.BOT_RESET_REQUEST_TYPE, p.BOT_RESET_REQUEST) and wIndex == p.INTERFACE:
                self.resets += 1
                self._phase = _IDLE
                self._needs_reset = False
                self._out.clear()
                return 0
            if (bmRequestType, bRequest) == (p.GET_MAX_LUN_REQUEST_TYPE, p.GET_MAX_LUN_REQUEST):
                return self._fill(data, b"\x00")
            raise _pipe_error()

    def _descriptor(self, kind: int, index: int) -> bytes:
        if kind == usb.util.DESC_TYPE_STRING:
            if index == 0:
                return bytes([4, 3, 0x09, 0x04])  # LANGID en-US
            strings = {**_STRINGS, 3: self.camera.identity.serial}
            if index not in strings:
                raise _pipe_error()
            text = strings[index].encode("utf-16-le")
            return bytes([2 + len(text), 3]) + text
        if kind == usb.util.DESC_TYPE_DEVICE:
            d = self.get_device_descriptor(self._device)
            return struct.pack("<BBHBBBBHHHBBBB", 18, 1, d.bcdUSB, 0, 0, 0, 64, d.idVendor, d.idProduct,
                               d.bcdDevice, 1, 2, 3, 1)
        raise _pipe_error()

    @staticmethod
    def _fill(data, reply: bytes) -> int:
        n = min(len(data), len(reply))
        data[:n] = type(data)("B", reply[:n])
        return n

    # -- bulk transfers ------------------------------------------------------------

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        self._check_present()
        with self._lock:
            payload = data.tobytes()
            self.wire.append(Transfer(ep, payload, len(payload)))
            if ep != p.EP_OUT or self.halted[p.EP_OUT]:
                raise _pipe_error()
            if self._phase == _IDLE:
                self._accept_cbw(payload)
            elif self._phase == _DATA_OUT:
                self._out += payload
                if len(self._out) >= self._cbw.data_length:
                    self._run(data_out=bytes(self._out[:self._cbw.data_length]))
                    self._phase = _STATUS
            else:  # the host is out of step: stall, as a device would
                self.halted[p.EP_OUT] = True
                raise _pipe_error()
            return len(payload)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        self._check_present()
        with self._lock:
            if ep != p.EP_IN or self.halted[p.EP_IN]:
                raise _pipe_error()
            if self._phase == _DATA_IN:
                n = self._send_data(buff)
            elif self._phase == _STATUS:
                n = self._send_csw(buff)
            else:  # nothing to send: a real device NAKs until the host gives up
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            self.wire.append(Transfer(ep, bytes(buff[:n]) if n <= _WIRE_DATA_LIMIT else b"", n))
            return n

    def _accept_cbw(self, payload: bytes) -> None:
        try:
            cbw = p.decode_cbw(payload)
        except ProtocolError:
            # BOT 6.6.1: an invalid CBW stalls both pipes until reset recovery.
            self._needs_reset = True
            self.halted[p.EP_IN] = self.halted[p.EP_OUT] = True
            return
        self._cbw = cbw
        if self._out:
            self._out.clear()
        self._hits = _NO_FAULTS
        if cbw.data_length and not cbw.direction_in:
            self._phase = _DATA_OUT
            return
        if cbw.cdb[:1] == bytes([p.OP_DOWNLOAD]):
            self._hits = self.faults.next_download()
        self._run(data_out=None)
        self._phase = _DATA_IN if cbw.direction_in and cbw.data_length else _STATUS

    def _run(self, *, data_out: bytes | None) -> None:
        cbw = self._cbw
        ok, reply = self.camera.handle(cbw.cdb, data_out=data_out,
                                       data_in_length=cbw.data_length if cbw.direction_in else 0)
        self._ok, self._reply = ok, reply
        self._residue = 0  # an OUT phase was taken whole; an IN phase sets it when sent

    def _send_data(self, buff) -> int:
        hits = self._hits
        if "gone" in hits:
            self.gone = True
            raise _no_device()
        if "timeout" in hits:
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        if "reset" in hits:
            self.camera.reboot()
            self._bus_reset()
            raise usb.core.USBError("Input/Output Error", -1, errno.EIO)
        if "stall" in hits:
            self.halted[p.EP_IN] = True
            self._ok, self._residue, self._phase = False, self._cbw.data_length, _STATUS
            raise _pipe_error()
        reply = self._reply if self._ok else b""
        n = min(len(buff) * buff.itemsize, len(reply))
        if "short" in hits:
            n = (n + 1) // 2
        memoryview(buff).cast("B")[:n] = reply[:n]
        self._residue = self._cbw.data_length - n
        self._phase = _STATUS
        return n

    def _send_csw(self, buff) -> int:
        hits = self._hits
        status = p.CSW_PASSED if self._ok else p.CSW_FAILED
        tag = self._cbw.tag
        if "phase_error" in hits:
            status = p.CSW_PHASE_ERROR
        if "bad_csw_tag" in hits:
            tag += 1
        csw = p.encode_csw(tag=tag, residue=self._residue, status=status)
        if "bad_csw_signature" in hits:
            csw = b"USBX" + csw[4:]
        n = min(len(buff), len(csw))
        memoryview(buff).cast("B")[:n] = csw[:n]
        self._phase = _IDLE
        return n

    def _clear_halt(self, ep: int) -> None:
        if ep not in self.halted:
            raise _pipe_error()
        if not self._needs_reset:
            self.halted[ep] = False

    def _bus_reset(self) -> None:
        self._phase = _IDLE
        self._needs_reset = False
        self.halted = {p.EP_IN: False, p.EP_OUT: False}
        self._out.clear()

    def _check_present(self) -> None:
        if self.gone:
            raise _no_device()
