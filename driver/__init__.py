"""plenodust driver: the Lytro F01 over USB and Wi-Fi, and a simulated camera.

Open a camera with :func:`open_usb`, :func:`open_wifi` or :func:`open_simulated`; each
returns a :class:`Camera`. The driver moves bytes; decoding them is :mod:`analysis`'s job.
"""

from driver.camera import Camera, CameraSettings, write_atomic
from driver.connect import open_simulated, open_usb, open_wifi
from driver.errors import (CameraBusy, CameraError, CameraFileNotFound, CameraGone, CameraNotFound,
                           CameraPermissionError, CameraTimeout, CommandFailed, IntegrityError, ProtocolError)
from driver.protocol import HardwareInfo, Picture

__all__ = [
    "Camera", "CameraSettings", "write_atomic", "open_usb", "open_wifi", "open_simulated",
    "CameraBusy", "CameraError", "CameraFileNotFound", "CameraGone", "CameraNotFound", "CameraPermissionError",
    "CameraTimeout", "CommandFailed", "IntegrityError", "ProtocolError", "HardwareInfo", "Picture",
]
