"""Exceptions a user of :mod:`analysis` can cause, each with a message that says what to do."""

from __future__ import annotations


class AnalysisError(Exception):
    """Base of every error raised by :mod:`analysis` for bad input or settings."""


class FormatError(AnalysisError, ValueError):
    """A file is not what it claims to be (LFP container, raw, metadata)."""


class TruncatedFileError(FormatError):
    """A file ends before a header or section it announces."""


class ChecksumError(FormatError):
    """A section's data does not match the SHA-1 in its header."""


class MissingSectionError(FormatError):
    """A section referenced by the table of contents is not in the file."""


class MetadataError(FormatError):
    """Metadata is not valid JSON or lacks a field the analysis needs."""


class RawSizeError(FormatError):
    """A raw sensor payload has the wrong number of bytes for its declared size."""


class MissingFileError(AnalysisError, FileNotFoundError):
    """A file another one needs is absent (the ``.TXT`` of a ``.RAW``, a bundle's ``nextFile``)."""


class CalibrationError(AnalysisError):
    """No usable calibration: no white image, a failed lattice fit, a bad cache."""


class NoWhiteImageError(CalibrationError):
    """No white image of the right camera (bright enough) was found."""


class CameraMismatchError(AnalysisError):
    """An exposure and a calibration come from different cameras."""


class ParameterError(AnalysisError, ValueError):
    """A pipeline or simulator parameter is out of its valid range."""


class TargetError(AnalysisError):
    """A calibration target's exposures cannot give a metric calibration."""


class TooFewDotsError(TargetError):
    """Too few of a target's dots were found in an exposure."""


class GridIdentificationError(TargetError):
    """A target's dots do not form one identifiable regular grid."""


class PositionMismatchError(TargetError, ValueError):
    """The stage positions given do not match the target's exposures."""


class TargetOutOfRangeError(TargetError):
    """A target position lies outside the range the camera can refocus to."""


class MetricCalibrationError(CalibrationError):
    """A metric (target) calibration file is unreadable or does not fit the exposure's camera."""
