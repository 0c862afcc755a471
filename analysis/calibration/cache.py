"""Calibrations kept on disk, keyed by camera serial and the white image's SHA-1, and the one call
that gives a picture its calibration (:func:`load_calibration`: choose the white image, read its
calibration from the cache or fit it, and add the camera's defect map, itself cached by the frames it
was found from: :mod:`analysis.calibration.camera_defects`)."""

from __future__ import annotations

import json
import logging
import re
import zipfile
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from analysis.cache import remove_older_versions
from analysis.camera.model import CameraModel, Lattice, Optics
from analysis.camera.second_stop import SecondStop
from analysis.errors import CalibrationError
from analysis.formats.atomic_write import atomic_path
from analysis.formats.mapped_npz import map_members
from analysis.formats.whites import WhiteImage, load_white_images

from .calibrate import Calibration, calibrate
from .camera_defects import camera_defects
from .profile import MicroImageProfile
from .white_choice import defect_search_frames, select_white_image

log = logging.getLogger(__name__)

# Bump when the cache file's content or meaning changes; it is part of the file name.
# 2: the micro-image profile (optical blur, aperture image radius, rim response) in the header.
# 3: the lattice fitted without the micro-images a second stop cuts (analysis.calibration.cut_lenses).
# 4: the second stop itself (analysis.calibration.second_stop_fit) in the header.
# 5: the second stop fitted with the optical blur's reach into the micro-images' central level.
CACHE_VERSION = 5


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
        "profile": None if calibration.profile is None else calibration.profile.to_dict(),
        "second_stop": None if calibration.second_stop is None else calibration.second_stop.to_dict(),
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
            # Mapped: the map (43 MB for an F01) only builds look-up tables, so a worker whose tables
            # come from their own cache never reads it into memory.
            mapped = map_members(path, ["devignetting"]).get("devignetting")
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
                           fit_centroid_rms_px=float(header["fit_centroid_rms_px"]), from_cache=True,
                           profile=None if header["profile"] is None else MicroImageProfile.from_dict(header["profile"]),
                           second_stop=None if header["second_stop"] is None else SecondStop.from_dict(header["second_stop"]))
    except CalibrationError:
        raise
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise CalibrationError(f"calibration file {path} is unreadable ({type(exc).__name__}: {exc}); "
                               "delete it, or let load_calibration rebuild it") from None


def load_calibration(source: Path, metadata: dict, *, serial: str | None = None,
                     cache_dir: Path | None = None, find_defects: bool = True) -> Calibration:
    """The calibration for a picture: white images loaded, one selected, fitted or read from cache,
    with the camera's defective pixels found from its white images (the dark ones included).

    Parameters
    ----------
    source : Path
        Folder of ``MOD_nnnn.RAW``/``.TXT`` white images, or a ``data.C.N`` bundle.
    metadata : dict
        Frame metadata of the picture.
    serial : str, optional, keyword-only
        The picture's camera serial.
    cache_dir : Path, optional, keyword-only
        Where calibrations are cached (``<serial>/<white_sha1>.v<version>.npz``, the defect map in
        ``<serial>/<frames key>.defects.v<version>.npz``); no caching if None. A cache file that
        cannot be read is logged, refitted and overwritten.
    find_defects : bool, keyword-only
        Search the camera's white images for hot, stuck and dead pixels
        (:func:`analysis.calibration.camera_defects.camera_defects`); False leaves ``defects`` None.

    Raises
    ------
    NoWhiteImageError, CameraMismatchError
        See :func:`select_white_image`.
    CalibrationError
        If the lattice fit fails.
    """
    whites = load_white_images(source)
    white = select_white_image(whites, metadata, serial=serial)
    calibration = cached_calibration(white, cache_dir=cache_dir, serial=serial, fallback_metadata=metadata)
    if not find_defects:
        return calibration
    frames = defect_search_frames(whites, white, metadata, serial=serial)
    defects = camera_defects(frames, calibration, cache_dir=cache_dir, serial=serial)
    return replace(calibration, defects=defects)


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
        remove_older_versions(path.parent, f"{calibration.white_sha1}.v", CACHE_VERSION)
    except OSError as exc:
        # A read-only or full cache folder costs time on the next call, not this result.
        log.warning("could not write calibration cache %s (%s); continuing without it", path, exc)
        return calibration
    # The devignetting map as just written, mapped (43 MB an F01's, read again only to build tables).
    mapped = map_members(path, ["devignetting"]).get("devignetting")
    if mapped is not None and (mapped.shape, mapped.dtype) == (calibration.devignetting.shape,
                                                               calibration.devignetting.dtype):
        calibration = replace(calibration, devignetting=mapped)
    return calibration
