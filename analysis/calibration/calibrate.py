"""Calibration of one camera at one zoom/focus from its white images.

Pick the white image (same camera; nearest ``zoomStep``, then nearest ``focusStep``; dark ones
skipped, lytro-f01.md 1.8), fit the global micro-image lattice to it (:mod:`analysis.calibration.lattice_fit`,
seeded from the white's own metadata model), keep the devignetting map, and cache the result
on disk keyed by camera serial and the white image's SHA-1.
"""

from __future__ import annotations

import json
import logging
import math
import re
import struct
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from analysis.formats.atomic_write import atomic_path
from analysis.camera.model import CameraModel, Lattice, Optics
from analysis.errors import CalibrationError, CameraMismatchError, MetadataError, NoWhiteImageError
from analysis.formats.frame_metadata import lookup
from .lattice_fit import LatticeFit, fit_lattice
from analysis.formats.raw12 import unpack12
from analysis.formats.whites import WhiteImage, load_white_images

log = logging.getLogger(__name__)

# LFToolbox drops F01 whites whose mean raw value is below this (LFUtilProcessWhiteImages.m).
DARK_MEAN_LEVEL = 500.0
# Bump when the cache file's content or meaning changes; it is part of the file name.
CACHE_VERSION = 1
_MLA_FIELDS = ("devices.mla.lensPitch", "devices.mla.rotation", "devices.mla.sensorOffset.x",
               "devices.mla.sensorOffset.y", "devices.mla.sensorOffset.z")


@dataclass(frozen=True, eq=False)
class Calibration:
    """Micro-image lattice and devignetting map of one camera at one zoom/focus.

    Attributes
    ----------
    serial : str or None
        Camera serial number of the white image (``None`` if its metadata has none).
    white_name, white_sha1 : str
        The white image used (e.g. ``MOD_0012``) and the SHA-1 of its packed raw bytes.
    zoom_step, focus_step : int or None
        Lens stepper positions of the white image.
    model : CameraModel
        The white image's metadata model with the fitted lattice. For an exposure, combine
        the exposure's optics with this lattice:
        ``CameraModel.from_metadata(meta).with_lattice(calibration.model.lattice)``.
    devignetting : ndarray of shape (H, W), float32
        ``(white - black) / (white_level - black)`` per pixel, not smoothed or clipped: the
        gaps between micro-images are near (or, by noise, below) zero, so divide only where it
        is above a floor.
    fit_rms_px : float
        RMS of the lattice-fit residuals in pixels.
    fit_n_lenses : int
        Lenses whose centroid agreed with the fitted lattice (within 1 px).
    fit_centroid_rms_px : float
        RMS distance between micro-image centroids and fitted centres (a check on the fit;
        centroids are noisier than the fit).
    from_cache : bool
        True when this calibration was read from the cache instead of fitted.
    """

    serial: str | None
    white_name: str
    white_sha1: str
    zoom_step: int | None
    focus_step: int | None
    model: CameraModel
    devignetting: np.ndarray
    fit_rms_px: float
    fit_n_lenses: int
    fit_centroid_rms_px: float
    from_cache: bool = False

    @property
    def lattice(self) -> Lattice:
        return self.model.lattice


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
    durations = [w.exposure_duration_s for w in mine if w.exposure_duration_s is not None]
    mean_duration = float(np.mean(durations)) if durations else None

    def short(w: WhiteImage) -> bool:
        d = w.exposure_duration_s
        return mean_duration is not None and d is not None and d < mean_duration * (1 - 1e-9)

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


def calibrate(white: WhiteImage, *, fallback_metadata: dict | None = None) -> Calibration:
    """Fit the lattice to a white image and keep its devignetting map.

    Parameters
    ----------
    white : WhiteImage
    fallback_metadata : dict, optional, keyword-only
        Frame metadata to seed the lattice from if the white's own metadata cannot (e.g. the
        picture's metadata, same camera).

    Raises
    ------
    MetadataError
        If neither metadata gives a camera model.
    CalibrationError
        If the lattice fit fails.
    """
    try:
        model = CameraModel.from_metadata(white.metadata)
    except MetadataError:
        if fallback_metadata is None:
            raise
        log.warning("white image %s: metadata gives no camera model; seeding from the picture's", white.name)
        model = CameraModel.from_metadata(fallback_metadata)
    raw = white.image()
    fit: LatticeFit = fit_lattice(raw, model.lattice, black_level=model.black_level)
    log.info("white image %s: lattice %s, fit rms %.4f px over %d blocks, %d lenses (centroid rms %.3f px)",
             white.name, fit.lattice, fit.rms_px, fit.n_blocks, fit.n_lenses, fit.centroid_rms_px)
    devignetting = raw.astype(np.float32)
    devignetting -= np.float32(model.black_level)
    devignetting *= np.float32(1.0 / (model.white_level - model.black_level))
    return Calibration(serial=white.serial, white_name=white.name, white_sha1=white.sha1,
                       zoom_step=white.zoom_step, focus_step=white.focus_step,
                       model=model.with_lattice(fit.lattice), devignetting=devignetting,
                       fit_rms_px=fit.rms_px, fit_n_lenses=fit.n_lenses,
                       fit_centroid_rms_px=fit.centroid_rms_px)


def cache_path(cache_dir: Path, serial: str | None, white_sha1: str) -> Path:
    """``cache_dir/<serial>/<white_sha1>.v<version>.npz`` (serial reduced to safe characters)."""
    safe = re.sub(r"[^A-Za-z0-9_-]", "_", serial) if serial else "unknown-serial"
    return Path(cache_dir) / safe / f"{white_sha1}.v{CACHE_VERSION}.npz"


def save_calibration(calibration: Calibration, path: Path) -> None:
    """Write a calibration to ``path`` (``.npz``) through a temp file and an atomic rename."""
    lat = calibration.model.lattice
    header = {
        "version": CACHE_VERSION, "serial": calibration.serial, "white_name": calibration.white_name,
        "white_sha1": calibration.white_sha1, "zoom_step": calibration.zoom_step,
        "focus_step": calibration.focus_step, "fit_rms_px": calibration.fit_rms_px,
        "fit_n_lenses": calibration.fit_n_lenses, "fit_centroid_rms_px": calibration.fit_centroid_rms_px,
        "lattice": {"origin_x": lat.origin_x, "origin_y": lat.origin_y, "pitch_px": lat.pitch_px,
                    "rotation_rad": lat.rotation_rad, "scale_x": lat.scale_x, "scale_y": lat.scale_y},
    }
    model = calibration.model
    header["model"] = {"width": model.width, "height": model.height, "black_level": model.black_level,
                       "white_level": model.white_level, "zoom_step": model.zoom_step,
                       "focus_step": model.focus_step, "optics": asdict(model.optics)}
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), devignetting=calibration.devignetting)


def read_calibration(path: Path, *, white_sha1: str | None = None) -> Calibration:
    """Read a calibration written by :func:`save_calibration`.

    Raises
    ------
    CalibrationError
        If the file is unreadable, of another version, or for another white image.
    """
    try:
        with np.load(path, allow_pickle=False) as npz:
            header: dict[str, Any] = json.loads(str(npz["header"]))
            mapped = _mapped_member(path, "devignetting")
            devignetting = npz["devignetting"] if mapped is None else mapped
        if header.get("version") != CACHE_VERSION:
            raise CalibrationError(f"{path} has cache version {header.get('version')}, not {CACHE_VERSION}; "
                                   "delete it, or let load_calibration rebuild it")
        if white_sha1 is not None and header["white_sha1"] != white_sha1:
            raise CalibrationError(f"{path} is for white image {header['white_sha1']}, not {white_sha1}; "
                                   "delete it, or let load_calibration rebuild it")
        m = header["model"]
        if devignetting.dtype != np.float32 or devignetting.shape != (m["height"], m["width"]):
            raise CalibrationError(f"{path} holds a {devignetting.dtype} {devignetting.shape} devignetting map, "
                                   "not the sensor's float32 one; delete it, or let load_calibration rebuild it")
        model = CameraModel(width=m["width"], height=m["height"], lattice=Lattice(**header["lattice"]),
                            optics=Optics(**m["optics"]), black_level=m["black_level"],
                            white_level=m["white_level"], zoom_step=m["zoom_step"], focus_step=m["focus_step"])
        return Calibration(serial=header["serial"], white_name=header["white_name"],
                           white_sha1=header["white_sha1"], zoom_step=header["zoom_step"],
                           focus_step=header["focus_step"], model=model, devignetting=devignetting,
                           fit_rms_px=float(header["fit_rms_px"]), fit_n_lenses=int(header["fit_n_lenses"]),
                           fit_centroid_rms_px=float(header["fit_centroid_rms_px"]), from_cache=True)
    except CalibrationError:
        raise
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise CalibrationError(f"calibration file {path} is unreadable ({type(exc).__name__}: {exc}); "
                               "delete it, or let load_calibration rebuild it") from None


def _mapped_member(path: Path, name: str) -> np.ndarray | None:
    """A read-only memory map of the ``.npy`` member ``name`` of an ``.npz`` file that stores it
    uncompressed (as :func:`save_calibration` writes it), else None.

    The devignetting map (43 MB for an F01) only builds look-up tables; mapped, a worker whose
    tables come from their own cache never reads it into memory.
    """
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(name + ".npy")
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as fh:
        fh.seek(info.header_offset)
        local = fh.read(30)  # the zip local file header: its name and extra field lengths at 26
        if len(local) < 30 or local[:4] != b"PK\x03\x04":
            return None
        name_len, extra_len = struct.unpack("<HH", local[26:30])
        fh.seek(info.header_offset + 30 + name_len + extra_len)
        version = np.lib.format.read_magic(fh)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, fortran, dtype = read_header(fh)
        offset = fh.tell()
    if dtype.hasobject or offset + dtype.itemsize * math.prod(shape) > path.stat().st_size:
        return None
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape,
                     order="F" if fortran else "C").view(np.ndarray)


def load_calibration(source: Path, metadata: dict, *, serial: str | None = None,
                     cache_dir: Path | None = None) -> Calibration:
    """The calibration for a picture: white images loaded, one selected, fitted or read from cache.

    Parameters
    ----------
    source : Path
        Folder of ``MOD_nnnn.RAW``/``.TXT`` white images, or a ``data.C.N`` bundle.
    metadata : dict
        Frame metadata of the picture.
    serial : str, optional, keyword-only
        The picture's camera serial.
    cache_dir : Path, optional, keyword-only
        Where calibrations are cached (``<serial>/<white_sha1>.v<version>.npz``); no caching
        if None. A cache file that cannot be read is logged, refitted and overwritten.

    Raises
    ------
    NoWhiteImageError, CameraMismatchError
        See :func:`select_white_image`.
    CalibrationError
        If the lattice fit fails.
    """
    white = select_white_image(load_white_images(source), metadata, serial=serial)
    return cached_calibration(white, cache_dir=cache_dir, serial=serial, fallback_metadata=metadata)


def cached_calibration(white: WhiteImage, *, cache_dir: Path | None, serial: str | None = None,
                       fallback_metadata: dict | None = None) -> Calibration:
    """:func:`calibrate` a white image, or read its calibration from ``cache_dir`` if there.

    The cache file is ``cache_dir/<serial>/<white_sha1>.v<version>.npz`` (the white's serial,
    else ``serial``). One that cannot be read is logged, refitted and overwritten; one that
    cannot be written is logged and skipped.
    """
    if cache_dir is None:
        return calibrate(white, fallback_metadata=fallback_metadata)
    sha1 = white.sha1
    path = cache_path(Path(cache_dir), white.serial or serial, sha1)
    if path.is_file():
        try:
            calibration = read_calibration(path, white_sha1=sha1)
            log.info("calibration for white image %s read from %s", white.name, path)
            return calibration
        except CalibrationError as exc:
            log.warning("calibration cache %s is unusable (%s); refitting and rewriting it", path, exc)
    calibration = calibrate(white, fallback_metadata=fallback_metadata)
    try:
        save_calibration(calibration, path)
    except OSError as exc:
        # A read-only or full cache folder costs time on the next call, not this result.
        log.warning("could not write calibration cache %s (%s); continuing without it", path, exc)
    return calibration
