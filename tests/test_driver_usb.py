"""The real driver against the simulated camera, through pyusb's own API (usb.core.find etc.).

Folders hold random bytes; what the driver returns is compared byte for byte with the
files, and the wire (CBWs, control requests) with the layouts of lytro-f01.md.
"""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import pytest
import usb.core
import usb.util

import driver
from driver import protocol as p
from driver.simulated import CameraFolder
from driver.simulated_usb import SimulatedBackend

RAW1_SIZE = 200_003  # not a multiple of any chunk size used here
CHUNK = 16 * 1024


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "camera"
    root.mkdir()
    rng = os.urandom
    (root / "IMG_0001.RAW").write_bytes(rng(RAW1_SIZE))
    (root / "IMG_0001.TXT").write_bytes(b'{"camera": {"model": "F01"}}')
    (root / "IMG_0001.128").write_bytes(rng(128 * 128 * 2))
    (root / "IMG_0002.RAW").write_bytes(rng(50_000))
    (root / "IMG_0002.TXT").write_bytes(b"{}")
    (root / "IMG_0001.truth.csv").write_bytes(b"ignored")
    (root / "notes.txt").write_bytes(b"ignored")
    cal = root / "calibration"
    cal.mkdir()
    for index in (0, 3):
        (cal / f"MOD_{index:04d}.RAW").write_bytes(rng(30_000 + index))
        (cal / f"MOD_{index:04d}.TXT").write_bytes(b'{"master": {}}')
    return root


@pytest.fixture()
def backend(folder: Path) -> SimulatedBackend:
    return SimulatedBackend(folder)


@pytest.fixture()
def camera(backend: SimulatedBackend):
    with driver.open_usb(backend, chunk_size=CHUNK, verify_id=True, ready_poll_s=0.001) as cam:
        yield cam


def cbws(backend: SimulatedBackend) -> list[p.CommandBlockWrapper]:
    return [p.decode_cbw(t.data) for t in backend.wire if t.endpoint == p.EP_OUT and t.data[:4] == b"USBC"]


def downloads(backend: SimulatedBackend) -> list[tuple[int, int]]:
    """(offset, requested length) of every download command on the wire."""
    return [(p.decode_cdb(c.cdb)[2], c.data_length) for c in cbws(backend) if c.cdb[0] == p.OP_DOWNLOAD]


def no_leftovers(dest: Path) -> bool:
    return not dest.exists() or not any(dest.iterdir())


# -- enumeration and set-up through pyusb ----------------------------------------------------


def test_pyusb_enumerates_the_simulated_camera_with_mass_storage_descriptors(backend):
    dev = usb.core.find(idVendor=0x24CF, idProduct=0x00A1, backend=backend)
    assert dev is not None
    cfg = dev[0]
    intf = cfg[(0, 0)]
    assert (intf.bInterfaceClass, intf.bInterfaceSubClass, intf.bInterfaceProtocol) == (0x08, 0x05, 0x50)
    addresses = sorted(ep.bEndpointAddress for ep in intf)
    assert addresses == [0x02, 0x82]
    assert all(usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK for ep in intf)
    assert usb.util.get_string(dev, dev.iManufacturer) == "Lytro, Inc."
    assert usb.core.find(idVendor=0x24CF, idProduct=0x00A2, backend=backend) is None


def test_open_detaches_the_kernel_driver_and_close_gives_it_back(backend):
    cam = driver.open_usb(backend)
    assert backend.kernel_driver_active[0] is False and backend.claimed == {0}
    assert backend.configuration == 1
    cam.close()
    assert backend.kernel_driver_active[0] is True and backend.claimed == set()


def test_open_without_a_camera_says_so(tmp_path):
    backend = SimulatedBackend(tmp_path)
    backend.gone = True
    with pytest.raises(driver.CameraNotFound, match="24cf:00a1"):
        driver.open_usb(backend)


def test_open_waits_for_test_unit_ready(backend):
    backend.camera.reboot(not_ready=3)
    with driver.open_usb(backend, ready_poll_s=0.001) as cam:
        assert cam.battery() == pytest.approx(87.5)
    turs = [c for c in cbws(backend) if not any(c.cdb)]
    assert len(turs) == 4  # three "not ready", then ready
    assert all(c.data_length == 0 and not c.direction_in for c in turs)


def test_open_gives_up_on_a_camera_that_never_becomes_ready(backend):
    backend.camera.reboot(not_ready=10**6)
    with pytest.raises(driver.CameraTimeout, match="not ready"):
        driver.open_usb(backend, ready_timeout_s=0.05, ready_poll_s=0.001)
    assert backend.kernel_driver_active[0] is True  # handed back on failure


# -- every command --------------------------------------------------------------------------


def test_info_battery_and_time(camera, backend):
    info = camera.info()
    assert (info.manufacturer, info.serial, info.software) == ("Lytro, Inc.", "A000000001", "v1.2.2")
    assert camera.battery() == pytest.approx(87.5)
    assert abs((camera.time() - backend.camera.clock()).total_seconds()) < 5
    wire = cbws(backend)
    # load hardware info (no data phase), query length (4 bytes IN), download (IN)
    assert any(c.cdb == bytes.fromhex("c20000") + bytes(13) and c.data_length == 0 for c in wire)
    assert any(c.cdb == bytes.fromhex("c60000") + bytes(13) and c.data_length == 4 and c.direction_in for c in wire)
    assert any(c.cdb == bytes.fromhex("c60006") + bytes(13) and c.data_length == 4 for c in wire)
    assert any(c.cdb == bytes.fromhex("c60003") + bytes(13) and c.data_length == 14 for c in wire)
    assert downloads(backend)[0] == (0, 644)


def test_picture_list_matches_the_folder(camera, folder):
    pictures = camera.pictures()
    assert [pic.name for pic in pictures] == ["IMG_0001", "IMG_0002"]
    for pic in pictures:
        raw = (folder / f"{pic.name}.RAW").read_bytes()
        assert pic.id == "sha1-" + hashlib.sha1(raw).hexdigest()
        assert pic.path == f"I:\\DCIM\\100PHOTO\\{pic.name}.RAW"
        assert abs(pic.taken.timestamp() - (folder / f"{pic.name}.RAW").stat().st_mtime) < 0.01


def test_load_file_sends_the_path_with_nul_as_an_out_phase(camera, backend, folder):
    camera.read_file("I:\\DCIM\\100PHOTO\\IMG_0001.TXT")
    wire = list(backend.wire)
    i = next(k for k, t in enumerate(wire) if t.data[:4] == b"USBC" and t.data[15:18] == bytes.fromhex("c20001"))
    path = b"I:\\DCIM\\100PHOTO\\IMG_0001.TXT\x00"
    tag = wire[i].data[4:8]
    assert wire[i].data == bytes.fromhex("55534243") + tag + bytes.fromhex("1e000000 00 00 10 c20001") + bytes(13)
    assert wire[i + 1].endpoint == 0x02 and wire[i + 1].data == path
    csw = p.decode_csw(wire[i + 2].data)
    assert wire[i + 2].endpoint == 0x82 and csw.tag == int.from_bytes(wire[i].data[4:8], "little") and csw.status == 0


def test_multi_chunk_download_is_byte_for_byte(camera, backend, folder):
    data = camera.read_file("I:\\DCIM\\100PHOTO\\IMG_0001.RAW")
    assert data == (folder / "IMG_0001.RAW").read_bytes()
    offsets = downloads(backend)
    n_full, rest = divmod(RAW1_SIZE, CHUNK)
    assert offsets == [(k * CHUNK, CHUNK) for k in range(n_full)] + [(n_full * CHUNK, rest)]
    # The second download command as sent, against section 2.1/2.2 byte by byte.
    sent = [t.data for t in backend.wire if t.data[:4] == b"USBC" and t.data[15] == 0xC4]
    tag = sent[1][4:8]
    expected = bytes.fromhex("55534243") + tag + bytes.fromhex("00400000 80 00 10 c4 00 01 00 40 00 00") + bytes(9)
    assert sent[1] == expected
    assert sent[-1][8:12] == rest.to_bytes(4, "little")


def test_twelve_byte_cdbs_work_too(backend, folder):
    with driver.open_usb(backend, cdb_length=12, chunk_size=CHUNK) as cam:
        assert cam.read_file("C:\\T1CALIB\\MOD_0003.RAW") == (folder / "calibration" / "MOD_0003.RAW").read_bytes()
    assert all(len(c.cdb) == 12 for c in cbws(backend))


def test_missing_file_is_reported_by_name(camera):
    with pytest.raises(driver.CameraFileNotFound, match="IMG_0099"):
        camera.read_file("I:\\DCIM\\100PHOTO\\IMG_0099.RAW")


def test_pull_writes_raw_txt_and_thumbnail_and_nothing_else(camera, folder, tmp_path):
    dest = tmp_path / "out"
    first, second = camera.pictures()
    written = camera.pull(first, dest)
    assert [f.name for f in written] == ["IMG_0001.RAW", "IMG_0001.TXT", "IMG_0001.128"]
    for f in written:
        assert f.read_bytes() == (folder / f.name).read_bytes()
    assert [f.name for f in camera.pull(second, dest)] == ["IMG_0002.RAW", "IMG_0002.TXT"]  # no .128
    assert sorted(f.name for f in dest.iterdir()) == sorted(
        ["IMG_0001.RAW", "IMG_0001.TXT", "IMG_0001.128", "IMG_0002.RAW", "IMG_0002.TXT"])


def test_pull_calibration_copies_the_white_images_present(camera, folder, tmp_path):
    written = camera.pull_calibration(tmp_path / "cal")
    assert sorted(f.name for f in written) == ["MOD_0000.RAW", "MOD_0000.TXT", "MOD_0003.RAW", "MOD_0003.TXT"]
    for f in written:
        assert f.read_bytes() == (folder / "calibration" / f.name).read_bytes()


def test_pull_checks_the_picture_id(camera, folder, tmp_path):
    pic = camera.pictures()[0]
    (folder / "IMG_0001.RAW").write_bytes(os.urandom(1000))  # replaced after listing
    with pytest.raises(driver.IntegrityError, match="hashes to"):
        camera.pull(pic, tmp_path / "out")
    assert no_leftovers(tmp_path / "out")


def test_watch_yields_new_pictures_as_they_appear(camera, folder):
    stop = threading.Event()
    before = {f.name for f in folder.iterdir()}

    def shoot():  # keep shooting until watch reports one, so no start-up race can hide it
        while not stop.wait(0.05):
            CameraFolder(folder).add_picture(os.urandom(1234), b"{}")

    threading.Thread(target=shoot).start()
    try:
        for pic in camera.watch(poll_s=0.02, stop=stop):
            stop.set()
    finally:
        stop.set()
    assert f"{pic.name}.RAW" not in before
    assert pic.id == "sha1-" + hashlib.sha1((folder / f"{pic.name}.RAW").read_bytes()).hexdigest()


def test_take_picture_calls_the_shutter_hook(folder):
    def shutter(cam_folder):
        cam_folder.add_picture(os.urandom(999), b"{}")

    with driver.open_simulated(folder, shutter=shutter) as cam:
        before = len(cam.pictures())
        cam.take_picture()
        assert len(cam.pictures()) == before + 1
    with driver.open_simulated(folder, retries=0) as cam:  # no shutter: the command fails
        with pytest.raises(driver.CommandFailed):
            cam.take_picture()


def test_sixteen_megabyte_raw_byte_for_byte(tmp_path):
    root = tmp_path / "big"
    root.mkdir()
    raw = os.urandom(16_137_600)  # an F01 raw: 3280 x 3280 x 12 bit
    (root / "IMG_0001.RAW").write_bytes(raw)
    (root / "IMG_0001.TXT").write_bytes(b"{}")
    with driver.open_simulated(root) as cam:
        written = cam.pull(cam.pictures()[0], tmp_path / "out")
    assert written[0].read_bytes() == raw


# -- faults ---------------------------------------------------------------------------------

RAW1 = "I:\\DCIM\\100PHOTO\\IMG_0001.RAW"


def test_stall_is_cleared_and_the_chunk_read_again(camera, backend, folder):
    backend.inject("stall", after=3)
    assert camera.read_file(RAW1) == (folder / "IMG_0001.RAW").read_bytes()
    assert (0x02, 0x01, 0, 0x82) in backend.control_log  # CLEAR_FEATURE(ENDPOINT_HALT) on bulk IN
    offsets = [o for o, _ in downloads(backend)]
    assert offsets.count(3 * CHUNK) == 2


def test_timeout_is_retried_after_reset_recovery(camera, backend, folder):
    backend.inject("timeout", after=2)
    assert camera.read_file(RAW1) == (folder / "IMG_0001.RAW").read_bytes()
    assert backend.resets == 1
    assert (0x21, 0xFF, 0, 0) in backend.control_log  # bulk-only mass storage reset
    assert backend.control_log.count((0x02, 0x01, 0, 0x82)) >= 1
    assert backend.control_log.count((0x02, 0x01, 0, 0x02)) >= 1


def test_persistent_timeout_ends_in_a_clear_camera_timeout_and_no_file(camera, backend, tmp_path):
    pic = camera.pictures()[0]
    backend.inject("timeout", count=None)
    with pytest.raises(driver.CameraTimeout, match="did not answer") as info:
        camera.pull(pic, tmp_path / "out")
    assert "4 times" in str(info.value)
    assert no_leftovers(tmp_path / "out")


def test_short_read_continues_from_the_offset_received(camera, backend, folder):
    backend.inject("short", after=1)
    assert camera.read_file(RAW1) == (folder / "IMG_0001.RAW").read_bytes()
    offsets = [o for o, _ in downloads(backend)]
    assert offsets[:3] == [0, CHUNK, CHUNK + CHUNK // 2]
    assert backend.resets == 0  # a short read is not an error


@pytest.mark.parametrize("kind", ["bad_csw_signature", "bad_csw_tag", "phase_error"])
def test_bad_status_wrapper_triggers_reset_recovery(camera, backend, folder, kind):
    backend.inject(kind, after=2)
    assert camera.read_file(RAW1) == (folder / "IMG_0001.RAW").read_bytes()
    assert backend.resets == 1


def test_persistent_stall_ends_in_a_clear_error(camera, backend):
    backend.inject("stall", count=None)
    with pytest.raises(driver.CommandFailed, match="failed at byte 0 .* 4 times in a row"):
        camera.read_file(RAW1)


def test_persistent_short_reads_still_give_the_whole_file(camera, backend, folder):
    backend.inject("short", count=None)
    assert camera.read_file(RAW1) == (folder / "IMG_0001.RAW").read_bytes()
    assert len(downloads(backend)) > 2 * (RAW1_SIZE // CHUNK)


def test_atomic_write_leaves_nothing_when_writing_fails(tmp_path):
    target = tmp_path / "IMG_0001.RAW"
    with pytest.raises(TypeError):
        driver.write_atomic(target, object())  # not bytes: fails after the temporary file exists
    assert list(tmp_path.iterdir()) == []
    target.write_bytes(b"old")
    driver.write_atomic(target, b"new")
    assert target.read_bytes() == b"new" and [f.name for f in tmp_path.iterdir()] == ["IMG_0001.RAW"]


def test_camera_gone_mid_download_raises_and_leaves_no_file(camera, backend, tmp_path):
    pic = camera.pictures()[0]
    backend.inject("gone", after=5)
    with pytest.raises(driver.CameraGone, match="reconnect"):
        camera.pull(pic, tmp_path / "out")
    assert no_leftovers(tmp_path / "out")
    with pytest.raises(driver.CameraNotFound):
        driver.open_usb(backend)


def test_camera_reset_mid_download_is_resumed_from_its_offset(camera, backend, folder):
    backend.inject("reset", after=4)
    assert camera.read_file(RAW1) == (folder / "IMG_0001.RAW").read_bytes()
    loads = [c for c in cbws(backend) if c.cdb[:3] == bytes.fromhex("c20001")]
    assert len(loads) == 2  # loaded again after the camera forgot it
    offsets = [o for o, _ in downloads(backend)]
    assert offsets.count(0) == 1 and offsets.count(4 * CHUNK) == 2  # resumed, not restarted
    turs = [c for c in cbws(backend) if not any(c.cdb)]
    assert len(turs) >= 1 + backend.camera.not_ready_after_reset + 1


def test_reset_while_pulling_a_picture_still_gives_exact_files(camera, backend, folder, tmp_path):
    pic = camera.pictures()[0]
    backend.inject("reset", after=2)
    backend.inject("stall", after=7)
    written = camera.pull(pic, tmp_path / "out")
    for f in written:
        assert f.read_bytes() == (folder / f.name).read_bytes()


def test_empty_camera_lists_no_pictures(tmp_path):
    with driver.open_simulated(tmp_path) as cam:
        assert cam.pictures() == []
        assert cam.pull_calibration(tmp_path / "cal") == []


def test_failed_claim_gives_the_kernel_driver_back(backend):
    backend.held_by_another_program = True
    with pytest.raises(driver.CameraBusy, match="another program"):
        driver.open_usb(backend)
    assert backend.kernel_driver_active[0] is True
