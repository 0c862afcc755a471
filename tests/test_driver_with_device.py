"""Checks against a real Lytro F01 on USB; skipped unless pytest runs with ``--camera``.

They only read (hardware info, battery, clock, picture list, one metadata file) and
write nothing to the camera.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone


def test_identity_battery_and_clock(real_camera):
    info = real_camera.info()
    assert info.serial.startswith("A")  # F01 serial numbers start with "A"
    assert 0.0 <= real_camera.battery() <= 100.0
    assert datetime(2011, 1, 1, tzinfo=timezone.utc) < real_camera.time()  # the F01 shipped in 2012


def test_picture_list_and_one_metadata_file(real_camera):
    pictures = real_camera.pictures()
    for pic in pictures:
        assert pic.path.startswith("I:\\DCIM\\") and pic.id.startswith("sha1-")
    if pictures:
        metadata = json.loads(bytes(real_camera.read_file(pictures[-1].path_for("TXT"))).rstrip(b"\0"))
        assert metadata["camera"]["model"] == "F01"
