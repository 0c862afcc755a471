"""Which white image calibrates a picture: same camera; nearest ``zoomStep``, then nearest
``focusStep``; dark ones skipped (lytro-f01.md 1.8)."""

from __future__ import annotations

import logging
import math
import os
from typing import Any, Callable

import numpy as np

from analysis.errors import CameraMismatchError, NoWhiteImageError
from analysis.formats.frame_metadata import lookup
from analysis.formats.raw12 import unpack12
from analysis.formats.whites import WhiteImage

log = logging.getLogger(__name__)

# LFToolbox drops F01 whites whose mean raw value is below this (LFUtilProcessWhiteImages.m).
DARK_MEAN_LEVEL = 500.0
_MLA_FIELDS = ("devices.mla.lensPitch", "devices.mla.rotation", "devices.mla.sensorOffset.x",
               "devices.mla.sensorOffset.y", "devices.mla.sensorOffset.z")


# Values computed from white images' raw bytes, per file state: a camera's calibration is looked up
# for every picture, and reading its white images each time would cost more than the rest.
_REMEMBERED: dict[tuple, Any] = {}
_REMEMBER_MAX = 1024


def remembered(white: WhiteImage, what: str, compute: Callable[[WhiteImage], Any]) -> Any:
    """``compute(white)``, remembered in this process while the white image's file is unchanged (same
    path, size and modification time); computed afresh for a white image held in memory."""
    source = white.raw_source
    if source is None:
        return compute(white)
    try:
        stat = os.stat(source.path)
    except OSError:
        return compute(white)
    key = (what, str(source.path), source.offset, source.length, stat.st_size, stat.st_mtime_ns)
    if key not in _REMEMBERED:
        if len(_REMEMBERED) >= _REMEMBER_MAX:
            _REMEMBERED.clear()
        _REMEMBERED[key] = compute(white)
    return _REMEMBERED[key]


def white_mean_level(white: WhiteImage, *, step: int = 16) -> float:
    """Mean raw value of a white image, from every ``step``-th pixel pair of its packed bytes."""
    buf = np.frombuffer(white.raw, dtype=np.uint8)
    triples = buf[: buf.size // 3 * 3].reshape(-1, 3)[::step]
    if triples.size == 0:
        return 0.0
    return float(unpack12(np.ascontiguousarray(triples), width=2 * len(triples), height=1).mean())


def _same_mla(a: dict, b: dict) -> bool | None:
    """Whether two metadata give the same factory MLA values; None if either lacks them."""
    for path in _MLA_FIELDS:
        va, vb = lookup(a, path), lookup(b, path)
        if va is None or vb is None:
            return None
        try:
            if not math.isclose(float(va), float(vb), rel_tol=1e-6, abs_tol=1e-15):
                return False
        except (TypeError, ValueError):
            return None
    return True


def _sensor_size(metadata: dict) -> tuple[Any, Any]:
    return lookup(metadata, "image.width"), lookup(metadata, "image.height")


def _of_this_camera(white: WhiteImage, metadata: dict, serial: str | None) -> bool:
    size, white_size = _sensor_size(metadata), _sensor_size(white.metadata)
    if None not in size and None not in white_size and size != white_size:
        return False
    if serial is not None and white.serial is not None:
        return white.serial == serial
    # Without a serial on one side, the MLA's factory geometry tells cameras apart.
    return _same_mla(white.metadata, metadata) is not False


def _describe(white: WhiteImage, metadata: dict) -> str:
    width, height = _sensor_size(white.metadata)
    mla = ", other MLA" if _same_mla(white.metadata, metadata) is False else ""
    return f"{white.serial or 'no serial'} ({width}x{height} px{mla})"


def _distance(value: int | None, target: int | None) -> float:
    if target is None:
        return 0.0
    return math.inf if value is None else abs(value - target)


def _short_exposure(whites: list[WhiteImage]) -> Callable[[WhiteImage], bool]:
    """Whether a white image was exposed shorter than the mean of ``whites`` (a dark one)."""
    durations = [w.exposure_duration_s for w in whites if w.exposure_duration_s is not None]
    mean_duration = float(np.mean(durations)) if durations else None

    def short(w: WhiteImage) -> bool:
        d = w.exposure_duration_s
        return mean_duration is not None and d is not None and d < mean_duration * (1 - 1e-9)

    return short


def defect_search_frames(whites: list[WhiteImage], chosen: WhiteImage, metadata: dict, *, serial: str | None = None,
                         max_bright: int = 4, max_dark: int = 2) -> list[tuple[WhiteImage, bool]]:
    """The frames of one camera that its pixel-defect search reads, each with whether it is dark.

    ``chosen`` (the picture's white image) first; then the camera's other bright white images and
    its dark ones (short exposure, or mean raw value below 500), nearest to ``chosen`` in
    ``zoomStep``, then ``focusStep``, at most ``max_bright`` bright frames in all and ``max_dark``
    dark ones (an F01 holds some 60 white images of 16 MB each; a few show its defects).

    Parameters
    ----------
    whites : list of WhiteImage
    chosen : WhiteImage
        From :func:`select_white_image`.
    metadata : dict
        Frame metadata of the picture (which camera).
    serial : str, optional, keyword-only
    max_bright, max_dark : int, keyword-only
    """
    mine = [w for w in whites if w is not chosen and _of_this_camera(w, metadata, serial)
            and w.raw_length == chosen.raw_length]
    short = _short_exposure(mine + [chosen])
    mine.sort(key=lambda w: (_distance(w.zoom_step, chosen.zoom_step), _distance(w.focus_step, chosen.focus_step),
                             w.name))
    frames: list[tuple[WhiteImage, bool]] = [(chosen, False)]
    n_bright, n_dark = 1, 0
    for w in mine:
        if n_bright >= max_bright and n_dark >= max_dark:
            break
        dark = short(w) or remembered(w, "mean level", white_mean_level) < DARK_MEAN_LEVEL
        if dark and n_dark < max_dark:
            frames.append((w, True))
            n_dark += 1
        elif not dark and n_bright < max_bright:
            frames.append((w, False))
            n_bright += 1
    return frames


def select_white_image(whites: list[WhiteImage], metadata: dict, *, serial: str | None = None) -> WhiteImage:
    """The white image to calibrate a picture with.

    Same camera (same sensor size; same serial where both sides have one, else the same MLA
    fields in the metadata); dark ones skipped (exposure shorter than the mean of this camera's
    whites, or mean raw value below 500, as LFToolbox does); then nearest ``zoomStep``, then
    nearest ``focusStep``.

    Parameters
    ----------
    whites : list of WhiteImage
    metadata : dict
        Frame metadata of the picture.
    serial : str, optional, keyword-only
        The picture's camera serial (from its private metadata).

    Raises
    ------
    NoWhiteImageError
        If the list is empty, or every white image of this camera is dark.
    CameraMismatchError
        If all white images come from other cameras.
    """
    if not whites:
        raise NoWhiteImageError("no white images given; pull the calibration files (MOD_*) from the camera")
    mine = [w for w in whites if _of_this_camera(w, metadata, serial)]
    if not mine:
        width, height = _sensor_size(metadata)
        others = sorted({_describe(w, metadata) for w in whites})
        raise CameraMismatchError(
            f"none of the {len(whites)} white image(s) is of camera {serial or '(no serial)'} with a "
            f"{width}x{height} px picture; found: {'; '.join(others)}. Pull the white images from this camera")
    short = _short_exposure(mine)
    candidates = [w for w in mine if not short(w)]
    zoom, focus = lookup(metadata, "devices.lens.zoomStep"), lookup(metadata, "devices.lens.focusStep")
    zoom = None if zoom is None else int(zoom)
    focus = None if focus is None else int(focus)
    candidates.sort(key=lambda w: (_distance(w.zoom_step, zoom), _distance(w.focus_step, focus), w.name))
    # Decode levels only in order of preference: usually the first candidate is bright.
    for w in candidates:
        level = white_mean_level(w)
        if level >= DARK_MEAN_LEVEL:
            return w
        log.info("white image %s skipped: mean raw value %.0f < %.0f", w.name, level, DARK_MEAN_LEVEL)
    raise NoWhiteImageError(
        f"all {len(mine)} white image(s) of camera {serial or 'of this picture'} are dark "
        f"({len(mine) - len(candidates)} with a short exposure, the rest with mean raw value < "
        f"{DARK_MEAN_LEVEL:.0f}); pull the camera's full calibration set (MOD_0000..MOD_0061)")
