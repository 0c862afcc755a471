"""The Lytro F01 command set over Wi-Fi (TCP), ``lytro-f01.md`` section 3.

Each command is a 28-byte header (magic ``0xFAAA55AF``, length, flags, the same 16-byte
command block as over USB) plus, for commands that send data, the payload. A command
that reads sets flag bit 0 and puts the reply-buffer size in ``length``; the camera
answers with a header (flag bit 1, the same command block) and ``length`` bytes of reply.
New-picture notices arrive as NUL-terminated text on the callback port (5677).

The Wi-Fi protocol has no TEST UNIT READY and no status: a connected socket is ready, and
a failure shows as an empty reply or a dropped connection.
"""

from __future__ import annotations

import logging
import socket
import threading
from typing import Callable

from driver import protocol as p
from driver.errors import CameraGone, CameraNotFound, CameraTimeout, ProtocolError

log = logging.getLogger(__name__)

CallbackListener = Callable[[str, str], None]
"""Called as ``listener(name, argument)``, e.g. ``("[NewPictureAvailable]", "sha1-...")``."""


def recv_exact(sock: socket.socket, n: int, into: bytearray | None = None) -> bytearray:
    """Exactly ``n`` bytes from ``sock`` (into ``into`` when given); the peer closing first is an error."""
    out = into if into is not None else bytearray(n)
    view = memoryview(out)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:n], n - got)
        if k == 0:
            raise ProtocolError(f"the camera closed the connection after {got} of {n} bytes")
        got += k
    return out


class WifiTransport:
    """Commands over TCP to a camera at ``host:port``, with an optional callback listener.

    Parameters
    ----------
    host : str
        The camera's address (10.100.1.1 on its own network).
    port : int
        Command port (5678).
    callback_port : int or None
        Port of the callback stream (5677); None to not listen.
    timeout_s : float
        Timeout of each socket operation.
    """

    cdb_length = 16

    def __init__(self, host: str, port: int = p.WIFI_COMMAND_PORT, *, callback_port: int | None = p.WIFI_CALLBACK_PORT,
                 timeout_s: float = 5.0) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        self.host, self.port, self.callback_port, self.timeout_s = host, port, callback_port, timeout_s
        self.listeners: list[CallbackListener] = []
        self._sock: socket.socket | None = None
        self._callback_sock: socket.socket | None = None
        self._callback_thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._reply = bytearray()

    # -- lifetime ------------------------------------------------------------------

    def open(self) -> None:
        """Connect the command socket and start listening for callbacks."""
        self._connect()
        if self.callback_port is not None:
            try:
                self._callback_sock = socket.create_connection((self.host, self.callback_port), self.timeout_s)
            except OSError as exc:
                log.warning("no callbacks from %s:%d (%s); new pictures are found by polling only",
                            self.host, self.callback_port, exc)
                return
            self._callback_sock.settimeout(None)
            self._callback_thread = threading.Thread(target=self._listen, name="lytro-callbacks", daemon=True)
            self._callback_thread.start()

    def close(self) -> None:
        self._closing.set()
        for sock in (self._sock, self._callback_sock):
            if sock is not None:
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()
        self._sock = self._callback_sock = None
        if self._callback_thread is not None:
            self._callback_thread.join(timeout=2.0)
            self._callback_thread = None

    def recover(self) -> None:
        """Reconnect the command socket (the camera drops it after errors and restarts).

        Raises
        ------
        CameraGone
            If the camera no longer accepts connections.
        """
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        try:
            self._connect()
        except CameraNotFound as exc:
            raise CameraGone(f"the camera at {self.host}:{self.port} went away; check that its Wi-Fi is "
                             f"still on (it turns off after 5 idle minutes) ({exc})") from exc

    # -- commands ------------------------------------------------------------------

    def execute(self, cdb: bytes, *, data_out: bytes | None = None, data_in_length: int = 0) -> memoryview:
        """Send one command; return the reply (empty for commands without one).

        An all-zero command block (TEST UNIT READY on USB) is answered locally: over
        Wi-Fi a connected camera is ready.
        """
        if data_out is not None and data_in_length:
            raise ValueError("a command either sends or receives data")
        if not any(cdb):
            if self._sock is None:
                raise ProtocolError("not connected")
            return memoryview(b"")
        if self._sock is None:
            self._connect()
        sock = self._sock
        command = bytes(cdb).ljust(16, b"\0")
        if data_in_length:
            message = p.encode_wifi_header(command, length=data_in_length, flags=p.WIFI_FLAG_READ)
        else:
            payload = data_out or b""
            message = p.encode_wifi_header(command, length=len(payload), flags=0) + payload
        try:
            sock.sendall(message)
            header = p.decode_wifi_header(bytes(recv_exact(sock, p.WIFI_HEADER_LENGTH)))
            if not header.flags & p.WIFI_FLAG_RESPONSE or header.command != command:
                raise ProtocolError(f"the reply (flags {header.flags:#x}, command {header.command[:3].hex()}) "
                                    f"does not answer command {command[:3].hex()}")
            if not data_in_length:
                return memoryview(b"")
            if header.length > data_in_length:
                raise ProtocolError(f"the camera announced {header.length} bytes for a "
                                    f"{data_in_length}-byte read")
            if len(self._reply) < header.length:
                self._reply = bytearray(header.length)
            recv_exact(sock, header.length, self._reply)
            return memoryview(self._reply)[:header.length]
        except socket.timeout as exc:
            self._drop()
            raise CameraTimeout(f"the camera at {self.host}:{self.port} did not answer within "
                                f"{self.timeout_s:g} s; move closer or raise timeout_s") from exc
        except ProtocolError:
            self._drop()
            raise
        except OSError as exc:
            self._drop()
            raise ProtocolError(f"connection to the camera failed: {exc}") from exc

    # -- internals -----------------------------------------------------------------

    def _connect(self) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), self.timeout_s)
        except OSError as exc:
            raise CameraNotFound(f"cannot reach a Lytro at {self.host}:{self.port} ({exc}); join the camera's "
                                 "Wi-Fi network (lytro.camera.*) and check the address") from exc
        sock.settimeout(self.timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock

    def _drop(self) -> None:
        # After a timeout or a torn frame the stream is out of step: start over on a new one.
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _listen(self) -> None:
        sock = self._callback_sock
        pending = bytearray()
        while not self._closing.is_set() and sock is not None:
            try:
                data = sock.recv(4096)
            except OSError:
                break
            if not data:
                break
            pending += data
            while b"\0" in pending:
                message, _, rest = bytes(pending).partition(b"\0")
                pending = bytearray(rest)
                name, arg = p.parse_callback(message)
                log.debug("callback %s %s", name, arg)
                for listener in list(self.listeners):
                    try:
                        listener(name, arg)
                    except Exception:  # a faulty listener must not stop the others
                        log.exception("callback listener failed")
