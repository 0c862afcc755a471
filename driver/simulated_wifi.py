"""A simulated Lytro F01 on Wi-Fi: a loopback TCP server speaking ``lytro-f01.md`` section 3.

:class:`SimulatedWifiServer` listens on a command port (framed commands, served by a
:class:`driver.simulated.SimulatedCamera`) and a callback port, where every connected client
receives ``[NewPictureAvailable] <id>`` (NUL-terminated) when a picture is taken with the
take-picture command or announced with :meth:`SimulatedWifiServer.announce`. Ports default
to free ones on 127.0.0.1, so tests can run in parallel.

Faults (:meth:`inject`) hit download commands: ``timeout`` (no answer), ``short`` (half the
bytes), ``reset`` (connection dropped, camera forgets what was loaded), ``gone`` (connection
dropped and the server stops listening).
"""

from __future__ import annotations

import logging
import os
import socket
import threading

from driver import protocol as p
from driver.errors import ProtocolError
from driver.simulated import CameraFolder, FaultPlan, SimulatedCamera
from driver.wifi import recv_exact

log = logging.getLogger(__name__)

_WIFI_FAULTS = {"timeout", "short", "reset", "gone"}


class SimulatedWifiServer:
    """A simulated camera on loopback TCP.

    Parameters
    ----------
    folder : path or CameraFolder, optional
        The camera's file system. Give this or ``camera``.
    camera : SimulatedCamera, optional
        A ready command engine.
    host : str
        Address to listen on.
    port, callback_port : int
        0 picks free ports; read them back from :attr:`port` and :attr:`callback_port`.
    **camera_settings
        Passed to :class:`SimulatedCamera` when ``folder`` is given (``shutter`` makes the
        take-picture command work).

    Examples
    --------
    >>> import tempfile
    >>> with SimulatedWifiServer(tempfile.mkdtemp()) as server:
    ...     server.port > 0
    True
    """

    def __init__(self, folder: str | os.PathLike | CameraFolder | None = None, *,
                 camera: SimulatedCamera | None = None, host: str = "127.0.0.1", port: int = 0,
                 callback_port: int = 0, **camera_settings) -> None:
        self.camera = SimulatedCamera.of(folder, camera, **camera_settings)
        self.faults = FaultPlan()
        self.host = host
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._commands = socket.create_server((host, port))
        self._callbacks = socket.create_server((host, callback_port))
        self.port = self._commands.getsockname()[1]
        self.callback_port = self._callbacks.getsockname()[1]
        self._callback_clients: list[socket.socket] = []
        self._connections: list[socket.socket] = []
        self._threads = [threading.Thread(target=self._accept_commands, name="sim-wifi-commands", daemon=True),
                         threading.Thread(target=self._accept_callbacks, name="sim-wifi-callbacks", daemon=True)]
        for thread in self._threads:
            thread.start()

    def __enter__(self) -> SimulatedWifiServer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def inject(self, kind: str, *, after: int = 0, count: int | None = 1) -> None:
        """Inject a fault into the download command ``after`` downloads from now."""
        if kind not in _WIFI_FAULTS:
            raise ValueError(f"fault {kind!r} does not exist over Wi-Fi; choose one of {sorted(_WIFI_FAULTS)}")
        with self._lock:
            self.faults.add(kind, after=after, count=count)

    def announce(self, picture_id: str) -> None:
        """Send ``[NewPictureAvailable] <picture_id>`` to every callback client."""
        message = f"{p.NEW_PICTURE_CALLBACK} {picture_id}".encode("ascii") + b"\0"
        with self._lock:
            clients = list(self._callback_clients)
        for client in clients:
            try:
                client.sendall(message)
            except OSError:
                with self._lock:
                    if client in self._callback_clients:
                        self._callback_clients.remove(client)

    def close(self) -> None:
        """Stop listening and drop every connection."""
        self._stop.set()
        self._close_listeners()
        with self._lock:
            sockets = self._connections + self._callback_clients
            self._connections, self._callback_clients = [], []
        for sock in sockets:
            _close(sock)
        for thread in self._threads:
            thread.join(timeout=2.0)

    # -- internals -----------------------------------------------------------------

    def _close_listeners(self) -> None:
        for server in (self._commands, self._callbacks):
            _close(server)

    def _accept_callbacks(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._callbacks.accept()
            except OSError:
                return
            with self._lock:
                self._callback_clients.append(client)

    def _accept_commands(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._commands.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._connections.append(conn)
            threading.Thread(target=self._serve, args=(conn,), name="sim-wifi-conn", daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            while not self._stop.is_set() and self._serve_one(conn):
                pass
        except (ProtocolError, OSError):
            pass  # the client went away or sent garbage: drop the connection, as the camera would
        finally:
            with self._lock:
                if conn in self._connections:
                    self._connections.remove(conn)
            _close(conn)

    def _serve_one(self, conn: socket.socket) -> bool:
        """Answer one framed command; False when the connection should end."""
        header = p.decode_wifi_header(bytes(recv_exact(conn, p.WIFI_HEADER_LENGTH)))
        reading = bool(header.flags & p.WIFI_FLAG_READ)
        data_out = None if reading else bytes(recv_exact(conn, header.length)) if header.length else b""
        hits: set[str] = set()
        with self._lock:
            if header.command[0] == p.OP_DOWNLOAD:
                hits = self.faults.next_download()
            if "gone" in hits:
                self._stop.set()
                self._close_listeners()
                return False
            if "reset" in hits:
                self.camera.reboot(not_ready=0)  # Wi-Fi has no TEST UNIT READY to wait on
                return False
            if "timeout" in hits:
                return True  # swallow the command; the client times out and reconnects
            taking = header.command[0] == p.OP_CONTROL
            before = {pic.id for pic in self.camera.folder.pictures()} if taking else set()
            ok, reply = self.camera.handle(header.command, data_out=data_out,
                                           data_in_length=header.length if reading else 0)
        if not ok:
            reply = b""
        if "short" in hits:
            reply = reply[:(len(reply) + 1) // 2]
        length = len(reply) if reading else header.length
        conn.sendall(p.encode_wifi_header(header.command, length=length, flags=p.WIFI_FLAG_RESPONSE))
        if reading and length:
            conn.sendall(reply)
        if taking:
            for pic in self.camera.folder.pictures():
                if pic.id not in before:
                    self.announce(pic.id)
        return True


def _close(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()
