"""`plenodust camera ...` against simulated cameras, and pull-then-process end to end."""

from __future__ import annotations

import csv
import json
import math
import os
import threading
from pathlib import Path

import pytest

from driver.simulated import CameraFolder
from driver.simulated_wifi import SimulatedWifiServer
from service.cli.main import main


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "camera"
    (root / "calibration").mkdir(parents=True)
    for n in (1, 2):
        (root / f"IMG_000{n}.RAW").write_bytes(os.urandom(70_000 + n))
        (root / f"IMG_000{n}.TXT").write_bytes(b"{}")
    (root / "calibration" / "MOD_0000.RAW").write_bytes(os.urandom(5000))
    (root / "calibration" / "MOD_0000.TXT").write_bytes(b"{}")
    return root


def test_info_and_list(folder, capsys):
    assert main(["camera", "info", "--simulated", str(folder)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["manufacturer"] == "Lytro, Inc." and info["battery_percent"] == 87.5
    assert main(["camera", "list", "--simulated", str(folder), "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["name"] for r in rows] == ["IMG_0001", "IMG_0002"]
    assert rows[0]["path"] == "I:\\DCIM\\100PHOTO\\IMG_0001.RAW"


def test_pull_by_name_latest_and_unknown(folder, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["camera", "pull", "--simulated", str(folder), "--out", str(out), "IMG_0002"]) == 0
    assert sorted(f.name for f in out.iterdir()) == ["IMG_0002.RAW", "IMG_0002.TXT"]
    assert (out / "IMG_0002.RAW").read_bytes() == (folder / "IMG_0002.RAW").read_bytes()
    assert main(["camera", "pull", "--simulated", str(folder), "--out", str(tmp_path / "l"), "--latest"]) == 0
    assert sorted(f.name for f in (tmp_path / "l").iterdir()) == ["IMG_0002.RAW", "IMG_0002.TXT"]
    capsys.readouterr()
    assert main(["camera", "pull", "--simulated", str(folder), "--out", str(out), "IMG_0042"]) == 1
    assert "IMG_0042" in capsys.readouterr().err


def test_calibration(folder, tmp_path, capsys):
    assert main(["camera", "calibration", "--simulated", str(folder), "--out", str(tmp_path / "cal")]) == 0
    assert sorted(f.name for f in (tmp_path / "cal").iterdir()) == ["MOD_0000.RAW", "MOD_0000.TXT"]


def test_watch_pulls_the_next_picture(folder, tmp_path, capsys):
    done = threading.Event()

    def shoot():  # keep shooting until watch has pulled one, so no start-up race can hide it
        while not done.wait(0.1):
            CameraFolder(folder).add_picture(os.urandom(3000), b'{"new": true}')

    threading.Thread(target=shoot).start()
    out = tmp_path / "out"
    try:
        assert main(["camera", "watch", "--simulated", str(folder), "--out", str(out), "--poll", "0.05",
                     "--count", "1"]) == 0
    finally:
        done.set()
    pulled = sorted(f.name for f in out.iterdir())
    assert len(pulled) == 2 and pulled[0].endswith(".RAW") and pulled[0] not in ("IMG_0001.RAW", "IMG_0002.RAW")
    assert (out / pulled[0]).read_bytes() == (folder / pulled[0]).read_bytes()


def test_wifi_option(folder, capsys):
    with SimulatedWifiServer(folder) as server:
        assert main(["camera", "list", "--wifi", f"127.0.0.1:{server.port}"]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == ["IMG_0001", "IMG_0002"]


def test_usb_without_a_camera_fails_with_advice(capsys):
    # No Lytro is attached to the machine running the tests (and libusb may be missing).
    assert main(["camera", "info", "--usb"]) == 1
    err = capsys.readouterr().err
    assert "24cf:00a1" in err or "libusb-1.0" in err


def test_pull_from_a_simulated_camera_then_process_gives_particles(tmp_path, capsys):
    pytest.importorskip("analysis.simulation.render")
    sim, pulled = tmp_path / "sim", tmp_path / "pulled"
    assert main(["simulate", "--out", str(sim), "--size", "800", "--quiet"]) == 0
    assert main(["camera", "pull", "--simulated", str(sim), "--out", str(pulled), "--quiet"]) == 0
    assert main(["camera", "calibration", "--simulated", str(sim), "--out", str(pulled / "cal"), "--quiet"]) == 0
    assert (pulled / "IMG_0001.RAW").read_bytes() == (sim / "IMG_0001.RAW").read_bytes()
    capsys.readouterr()
    table = tmp_path / "particles.csv"
    assert main(["process", str(pulled / "IMG_0001.RAW"), "--calibration", str(pulled / "cal"),
                 "--out", str(table), "--quiet", "--no-cache"]) == 0
    with table.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) > 0
    assert {"X", "Y", "Z"} <= set(rows[0])
    # The pulled exposure is the simulated one: every true particle is found where it is
    # (laterally; depth accuracy is the pipeline's own tests' business).
    with (sim / "IMG_0001.truth.csv").open() as f:
        truth = list(csv.DictReader(f))
    for particle in truth:
        nearest = min(math.hypot(float(r["X"]) - float(particle["X"]), float(r["Y"]) - float(particle["Y"]))
                      for r in rows)
        assert nearest < 0.1, f"particle {particle['particle']} not found (nearest {nearest:.3f} mm)"
