"""Exceptions a user of :mod:`driver` can meet, each with a message that says what to do.

Every one is a :class:`CameraError`, itself an :class:`IOError`, so callers that only care
that "the camera did not deliver" can catch one thing.
"""

from __future__ import annotations


class CameraError(IOError):
    """Base of every error raised by :mod:`driver`."""


class CameraNotFound(CameraError):
    """No Lytro F01 (24cf:00a1) is connected, or it cannot be reached over Wi-Fi."""


class CameraTimeout(CameraError):
    """The camera did not answer within the timeout, even after the retries."""


class CameraGone(CameraError):
    """The camera went away (unplugged, switched off, Wi-Fi dropped) during a command."""


class ProtocolError(CameraError):
    """The camera answered something the protocol does not allow (bad wrapper, wrong tag)."""


class CommandFailed(CameraError):
    """The camera reported that a command failed (status wrapper status 1)."""


class CameraFileNotFound(CameraError, FileNotFoundError):
    """The camera has no file at the requested path (it reports length 0)."""


class IntegrityError(CameraError):
    """Downloaded bytes do not match the announced length or the picture's SHA-1."""


class CameraBusy(CameraError):
    """Another program (or a kernel driver that would not let go) holds the camera's interface."""


class CameraPermissionError(CameraError, PermissionError):
    """The operating system refused access to the USB device."""
