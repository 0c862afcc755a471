"""The driver over Wi-Fi against the simulated camera on loopback TCP (real sockets)."""

from __future__ import annotations

import hashlib
import os
import socket
import threading
from pathlib import Path

import pytest

import driver
from driver import protocol as p
from driver.simulated import CameraFolder
from driver.simulated_wifi import SimulatedWifiServer

CHUNK = 8 * 1024
RAW_SIZE = 100_001


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "camera"
    (root / "calibration").mkdir(parents=True)
    (root / "IMG_0001.RAW").write_bytes(os.urandom(RAW_SIZE))
    (root / "IMG_0001.TXT").write_bytes(b'{"image": {}}')
    (root / "calibration" / "MOD_0007.RAW").write_bytes(os.urandom(9000))
    (root / "calibration" / "MOD_0007.TXT").write_bytes(b"{}")
    return root


def shutter(cam_folder: CameraFolder) -> None:
    cam_folder.add_picture(os.urandom(4321), b'{"new": true}')


@pytest.fixture()
def server(folder: Path):
    with SimulatedWifiServer(folder, shutter=shutter) as srv:
        yield srv


@pytest.fixture()
def camera(server: SimulatedWifiServer):
    cam = driver.open_wifi("127.0.0.1", server.port, callback_port=server.callback_port, chunk_size=CHUNK,
                           timeout_s=0.5, verify_id=True)
    yield cam
    cam.close()


def test_commands_over_tcp(camera, server, folder, tmp_path):
    assert camera.info().serial == server.camera.identity.serial
    assert camera.battery() == pytest.approx(87.5)
    pictures = camera.pictures()
    assert [pic.name for pic in pictures] == ["IMG_0001"]
    written = camera.pull(pictures[0], tmp_path / "out")
    assert [f.read_bytes() for f in written] == [(folder / f.name).read_bytes() for f in written]
    cal = camera.pull_calibration(tmp_path / "cal")
    assert sorted(f.name for f in cal) == ["MOD_0007.RAW", "MOD_0007.TXT"]
    assert all(f.read_bytes() == (folder / "calibration" / f.name).read_bytes() for f in cal)
    downloads = [c for c in server.camera.commands if c[0] == p.OP_DOWNLOAD]
    assert all(c[2] == 1 for c in downloads)  # lyli/pyly's byte 2 by default


def test_kucera_download_variant_is_a_setting(folder):
    with SimulatedWifiServer(folder, download_subcode=0) as srv:
        cam = driver.open_wifi("127.0.0.1", srv.port, callback_port=None, download_subcode=0, chunk_size=CHUNK)
        try:
            assert cam.read_file("I:\\DCIM\\100PHOTO\\IMG_0001.RAW") == (folder / "IMG_0001.RAW").read_bytes()
        finally:
            cam.close()
        assert {c[2] for c in srv.camera.commands if c[0] == p.OP_DOWNLOAD} == {0}


def test_the_frames_on_the_wire(folder):
    """A raw socket client, framing written out by hand from section 3."""
    with SimulatedWifiServer(folder) as srv, socket.create_connection(("127.0.0.1", srv.port), 2) as s:
        s.sendall(bytes.fromhex("af55aafa 04000000 01000000 c60006") + bytes(13))
        reply = b""
        while len(reply) < 28 + 4:  # header and payload may come in separate segments
            part = s.recv(28 + 4 - len(reply))
            assert part, "connection closed early"
            reply += part
        assert reply[:28] == bytes.fromhex("af55aafa 04000000 02000000 c60006") + bytes(13)
        assert reply[28:] == bytes.fromhex("00 00 af 42")  # 87.5 as float32 LE


def test_new_picture_callback_wakes_watch(camera, server, folder):
    heard = []
    camera.transport.listeners.append(lambda name, arg: heard.append((name, arg)))
    stop = threading.Event()
    threading.Timer(0.05, camera.take_picture).start()
    for pic in camera.watch(poll_s=30.0, stop=stop):  # a long poll: only the callback can wake it in time
        stop.set()
    assert pic.name == "IMG_0002"
    assert pic.id == "sha1-" + hashlib.sha1((folder / "IMG_0002.RAW").read_bytes()).hexdigest()
    assert heard == [("[NewPictureAvailable]", pic.id)]


@pytest.mark.parametrize("kind", ["short", "reset", "timeout"])
def test_faults_are_recovered(camera, server, folder, kind):
    server.inject(kind, after=3)
    assert camera.read_file("I:\\DCIM\\100PHOTO\\IMG_0001.RAW") == (folder / "IMG_0001.RAW").read_bytes()
    offsets = [p.decode_cdb(c)[2] for c in server.camera.commands if c[0] == p.OP_DOWNLOAD]
    assert offsets[0] == 0 and offsets[-1] < RAW_SIZE
    if kind == "short":
        assert CHUNK * 3 + CHUNK // 2 in offsets
    else:
        # The failed command never reached the camera; the download went on from its offset
        # (each chunk served once), after a reconnect and a second load.
        assert sorted(set(offsets)) == list(range(0, RAW_SIZE, CHUNK)) and offsets.count(0) == 1
        loads = [c for c in server.camera.commands if c[:3] == bytes.fromhex("c20001")]
        assert len(loads) == 2


def test_camera_gone_leaves_no_file(camera, server, tmp_path):
    pic = camera.pictures()[0]
    server.inject("gone", after=2)
    with pytest.raises(driver.CameraGone, match="went away"):
        camera.pull(pic, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_unreachable_camera():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here
    with pytest.raises(driver.CameraNotFound, match="Wi-Fi"):
        driver.open_wifi("127.0.0.1", port, callback_port=None, timeout_s=0.5)
